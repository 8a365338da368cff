"""Square crops around a mask and area resampling, applied alike to images, masks and normals."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pstoolkit import UserError
from pstoolkit.grid import area_weights


@dataclass(frozen=True)
class Square:
    """A square window of ``side`` pixels whose top-left pixel is (``top`` row, ``left`` column); it
    may reach outside the image, where crops are padded with zeros."""

    top: int
    left: int
    side: int


def square_around(mask: np.ndarray, margin_px: int) -> Square:
    """The square around the mask's bounding box with ``margin_px`` on each side of its longer edge,
    centred on the box."""
    rows, cols = np.nonzero(mask)
    if rows.size == 0:
        raise UserError("the mask is empty: nothing to crop around")
    side = int(max(np.ptp(rows), np.ptp(cols))) + 1 + 2 * margin_px
    top = (int(rows.min()) + int(rows.max()) + 1 - side) // 2
    left = (int(cols.min()) + int(cols.max()) + 1 - side) // 2
    return Square(top, left, side)


def crop(image: np.ndarray, square: Square) -> np.ndarray:
    """The (side, side, …) window of an (H, W, …) array, zeros where it leaves the image."""
    height, width = image.shape[:2]
    out = np.zeros((square.side, square.side, *image.shape[2:]), dtype=image.dtype)
    r0, r1 = max(square.top, 0), min(square.top + square.side, height)
    c0, c1 = max(square.left, 0), min(square.left + square.side, width)
    if r1 > r0 and c1 > c0:
        out[r0 - square.top : r1 - square.top, c0 - square.left : c1 - square.left] = image[r0:r1, c0:c1]
    return out


def area_resize(image: np.ndarray, size: int) -> np.ndarray:
    """An (n, n, …) array area-averaged onto size×size pixels (each target pixel the mean of the
    source area it covers), float32."""
    n = image.shape[0]
    weights = area_weights(size, n, size / n).astype(np.float32)
    rows = np.tensordot(weights, np.asarray(image, dtype=np.float32), axes=(1, 0))
    return np.swapaxes(np.tensordot(weights, rows, axes=(1, 1)), 0, 1)


def resize_truth(normal: np.ndarray | None, mask: np.ndarray, size: int) -> tuple[np.ndarray | None, np.ndarray]:
    """Ground truth of a square (n, n) window at size×size: the mask where at least half of a target
    pixel was inside, normals area-averaged and re-normalised (0 outside the mask)."""
    small_mask = area_resize(mask.astype(np.float32), size) >= 0.5
    if normal is None:
        return None, small_mask
    n = area_resize(normal, size)
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    small_mask &= norm[..., 0] > 1e-6
    return np.where(small_mask[..., None], n / np.maximum(norm, 1e-12), 0.0).astype(np.float32), small_mask
