"""Accuracy of normal maps: per-pixel angular error and the summary statistics papers report; and of
depth maps: RMSE after the usual scale/offset alignment (``depth_error``).

MAE is the mean of the per-pixel angles (DiLiGenT's definition), not the arccos of the mean cosine.
A pixel a solver leaves unsolved (a zero normal) counts as 90° in the MAE, the median and the shares
under 11.25°, 22.5° and 30° (the thresholds normal-estimation papers quote); the coverage (share of
pixels solved) and the MAE over the solved pixels say how much of the error that is.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from pstoolkit._shared.vectors import unit
from pstoolkit.errors import UserError

THRESHOLDS_DEG = (11.25, 22.5, 30.0)
SHARE_KEYS = tuple(f"below_{threshold:g}".replace(".", "_") for threshold in THRESHOLDS_DEG)
"""The statistics' names of the shares under each threshold: below_11_25, below_22_5, below_30."""


@dataclass
class DepthError:
    """``depth_error``'s result: ``rmse`` in the truth's units after alignment, the ``scale`` and
    ``offset`` that align the depth to the truth (truth ≈ scale·depth + offset), and the number of
    ``pixels`` compared."""

    rmse: float
    scale: float
    offset: float
    pixels: int


def depth_error(depth: np.ndarray, truth: np.ndarray, mask: np.ndarray, *, scale: bool = True) -> DepthError:
    """RMSE of a depth map against the truth after the usual scale/offset alignment.

    Integrated depth is known only up to an offset (orthographic) or a scale (perspective), and may
    be in other units than the truth (pixels against mm), so before comparing, the least-squares
    ``s``, ``o`` minimising Σ (s·depth + o − truth)² over the pixels of ``mask`` where both maps are
    finite are applied (``scale=False``: s = 1, only the offset is fitted); the RMSE of
    s·depth + o − truth over them is returned in the truth's units. The scale may come out negative
    (a depth of the opposite sign convention); a depth constant over the pixels gets s = 0 (it
    explains nothing of the truth's shape). Raises UserError when the shapes differ or no pixel is
    left to compare.

    Parameters
    ----------
    depth
        (H, W) the depth to rate (NaN where there is none).
    truth
        (H, W) the true depth.
    mask
        (H, W) bool, the pixels to compare.
    scale
        Fit a scale as well as the offset.
    """
    d = np.asarray(depth, dtype=np.float64)
    t = np.asarray(truth, dtype=np.float64)
    m = np.asarray(mask, dtype=bool)
    if d.shape != t.shape or m.shape != t.shape or d.ndim != 2:
        raise UserError(f"depth {d.shape}, truth {t.shape} and mask {m.shape} must be equal (H, W)")
    inside = m & np.isfinite(d) & np.isfinite(t)
    if not inside.any():
        raise UserError("no pixels to compare: the mask has none where both depths are finite")
    d, t = d[inside], t[inside]
    # centred sums: the fit of s stays exact for depths far from 0 (perspective: z ≈ −f)
    dc, tc = d - d.mean(), t - t.mean()
    spread = float(np.dot(dc, dc))
    s = (float(np.dot(dc, tc)) / spread if spread > 0 else 0.0) if scale else 1.0
    o = float(t.mean() - s * d.mean())
    residual = s * d + o - t
    return DepthError(rmse=float(np.sqrt(np.mean(residual**2))), scale=s, offset=o, pixels=int(d.size))


def angular_error_deg(normal: np.ndarray, normal_gt: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Angle in degrees between two normal maps (..., 3), per pixel: an error map of shape (...) with
    NaN outside ``mask`` (all pixels when None). Both maps are normalised first; a zero normal counts
    as 90° off."""
    a = np.asarray(normal, dtype=np.float64)
    b = np.asarray(normal_gt, dtype=np.float64)
    if a.shape != b.shape or a.shape[-1:] != (3,):
        raise UserError(f"normal maps of shape {a.shape} and {b.shape} cannot be compared (expected equal (..., 3))")
    cosine = np.clip(np.sum(unit(a) * unit(b), axis=-1), -1.0, 1.0)
    errors = np.degrees(np.arccos(cosine))
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != errors.shape:
            raise UserError(f"mask of shape {mask.shape} does not fit normal maps of shape {a.shape}")
        errors[~mask] = np.nan
    return errors


def error_stats(errors: np.ndarray, solved: np.ndarray | None = None) -> dict[str, Any]:
    """Summary of angular errors in degrees over the pixels that are not NaN (NaN: outside the mask):
    ``mae_deg``, ``median_deg``, ``p90_deg`` (the 90th percentile: where the tails are), the shares (0..1) of pixels with an error under each of
    ``THRESHOLDS_DEG`` (``SHARE_KEYS``), ``n_pixels``, ``coverage`` (share of them in ``solved``, a
    bool map of the shape of ``errors``; all when None) and ``mae_solved_deg`` (MAE over those; None
    when there are none)."""
    values = np.asarray(errors, dtype=np.float64).ravel()
    inside = ~np.isnan(values)
    if not inside.any():
        raise UserError("no pixels to evaluate: the mask is empty")
    done = np.ones(values.size, dtype=bool) if solved is None else np.asarray(solved, dtype=bool).ravel()
    if done.size != values.size:
        raise UserError(f"solved map of {done.size} pixels does not fit an error map of {values.size}")
    values, done = values[inside], done[inside]
    stats: dict[str, Any] = {"mae_deg": float(values.mean()), "median_deg": float(np.median(values)),
                             "p90_deg": float(np.percentile(values, 90))}
    for threshold, key in zip(THRESHOLDS_DEG, SHARE_KEYS):
        stats[key] = float(np.count_nonzero(values < threshold) / values.size)
    stats["n_pixels"] = int(values.size)
    stats["coverage"] = float(np.count_nonzero(done) / values.size)
    stats["mae_solved_deg"] = float(values[done].mean()) if done.any() else None
    return stats


def rim_band(mask: np.ndarray, share: float = 0.05) -> np.ndarray:
    """(H, W) bool: the pixels of ``mask`` within ``share`` of the object's radius of its outline, the
    radius taken as that of a disc of the mask's area (a sphere's outer 5 % at the default)."""
    import cv2  # deferred: only this band needs the distance transform

    mask = np.asarray(mask, dtype=bool)
    radius = np.sqrt(mask.sum() / np.pi)
    inside = cv2.distanceTransform(np.pad(mask, 1).astype(np.uint8), cv2.DIST_L2, 5)[1:-1, 1:-1]
    return mask & (inside <= max(share * radius, 1.0))


def highlight_band(normal: np.ndarray, mask: np.ndarray, directions: np.ndarray, roughness: float | np.ndarray,
                   view: np.ndarray = np.array([0.0, 0.0, 1.0]), level: float = 0.1) -> np.ndarray:
    """The pixels of ``mask`` a GGX highlight passes over while the light takes the given directions: at
    some moment the pixel is lit and its lobe D(n·h) is at least ``level`` of its peak.

    Parameters
    ----------
    normal
        (H, W, 3) unit normals.
    mask
        (H, W) bool, the object's pixels.
    directions
        (T, 3) unit directions to the light.
    roughness
        GGX roughness r, a number or an (H, W) map (clamped to ≥ 0.02, as in ``pstoolkit.optics.brdf``).
    view
        Unit direction to the viewer (default +z).
    level
        Share of the lobe's peak D(0) that counts as in the highlight.

    Returns
    -------
    numpy.ndarray
        (H, W) bool, False outside ``mask``.
    """
    mask = np.asarray(mask, dtype=bool)
    n = np.asarray(normal, dtype=np.float64)[mask]
    r = np.broadcast_to(np.asarray(roughness, dtype=np.float64), mask.shape)[mask]
    alpha2 = np.maximum(r, 0.02) ** 4
    half = np.asarray(directions, dtype=np.float64) + np.asarray(view, dtype=np.float64)
    half /= np.linalg.norm(half, axis=-1, keepdims=True)
    hit = np.zeros(n.shape[0], dtype=bool)
    for start in range(0, half.shape[0], 64):
        cos_h = np.clip(n @ half[start : start + 64].T, 0.0, 1.0)
        lit = n @ np.asarray(directions, dtype=np.float64)[start : start + 64].T > 0
        # D(θ)/D(0) = α⁴ / (cos²θ·(α² − 1) + 1)² with α² = r⁴ (pstoolkit.optics.brdf's GGX)
        ratio = (alpha2[:, None] / (cos_h**2 * (alpha2[:, None] - 1.0) + 1.0)) ** 2
        hit |= np.any(lit & (ratio >= level), axis=1)
    out = np.zeros(mask.shape, dtype=bool)
    out[mask] = hit
    return out
