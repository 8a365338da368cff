"""Small DiLiGenT- and DiLiGenT-Π-layout folders rendered from a known shape, for converter tests.

A Lambertian sphere cap with a Gaussian bump and a smooth RGB albedo, rendered under DiLiGenT's
12×8 light grid (id = 8·column + row) with per-light RGB intensities, written exactly as the
datasets lay it out (Shi et al. 2016; docs/converters.md): 16-bit PNGs written by OpenCV (so BGR on disk), ``filenames.txt``,
``light_directions.txt``, ``light_intensities.txt`` (RGB order), ``mask.png`` (uint8, 3 channels,
0/255) and ``Normal_gt.mat`` (float64 (H, W, 3), 0 outside the mask). The cap stays within 50° of
the view and the lights within 33° of it, so no pixel is in attached shadow under any light.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import scipy.io

GRID_COLUMNS, GRID_ROWS = 12, 8
PI_SIDE = 10
WHITE = 0.8 * 65535


@dataclass
class Fixture:
    """What a fixture folder was rendered from: normals (H, W, 3) and mask (H, W) as in
    ``Normal_gt.mat``, RGB albedo (H, W, 3), unit light directions and RGB intensities (K, 3), and the
    linear 16-bit RGB images (K, H, W, 3) before rounding."""

    folder: Path
    normal: np.ndarray
    mask: np.ndarray
    albedo: np.ndarray
    directions: np.ndarray
    intensities: np.ndarray
    radiance: np.ndarray


def diligent_directions() -> np.ndarray:
    """(96, 3) unit directions of a 12×8 grid in front of the object. The boundary loop of the semi-real recipe
    (88…95, 87, 79, …, 80) runs around the grid's physical edge, which places index column c at
    physical column 11 − c for c ≥ 6 and 6 + c for c < 6; row 0 is at the top."""
    ids = np.arange(GRID_COLUMNS * GRID_ROWS)
    column, row = ids // GRID_ROWS, ids % GRID_ROWS
    place = np.where(column >= 6, 11 - column, 6 + column)
    vectors = np.stack([(place - 5.5) * 0.1, (3.5 - row) * 0.1, np.ones(ids.size)], axis=-1)
    return vectors / np.linalg.norm(vectors, axis=-1, keepdims=True)


def pi_directions() -> np.ndarray:
    """(100, 3) unit directions of a 10×10 grid, as DiLiGenT-Π's 100 lights."""
    v, u = np.mgrid[0:PI_SIDE, 0:PI_SIDE]
    vectors = np.stack([(u.ravel() - 4.5) * 0.1, (4.5 - v.ravel()) * 0.1, np.ones(PI_SIDE * PI_SIDE)], axis=-1)
    return vectors / np.linalg.norm(vectors, axis=-1, keepdims=True)


def shape(height: int, width: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normals (camera frame, y up), mask and RGB albedo of a sphere cap with a bump."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    radius = 0.42 * min(height, width) / np.sin(np.radians(50.0))
    x, y = u - (width - 1) / 2.0, (height - 1) / 2.0 - v
    mask = x * x + y * y <= (radius * np.sin(np.radians(50.0))) ** 2
    z = np.sqrt(np.clip(radius * radius - x * x - y * y, 1.0, None))
    sigma = 0.12 * min(height, width)
    bump = 0.35 * sigma * np.exp(-((x - 0.25 * radius) ** 2 + (y - 0.2 * radius) ** 2) / (2 * sigma * sigma))
    dz_dx = -x / z - bump * (x - 0.25 * radius) / sigma**2
    dz_dy = -y / z - bump * (y - 0.2 * radius) / sigma**2
    normal = np.stack([-dz_dx, -dz_dy, np.ones_like(z)], axis=-1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    normal[~mask] = 0.0
    albedo = np.stack([0.9 - 0.3 * (u / width), 0.5 + 0.3 * (v / height), 0.4 + 0.2 * (u / width)], axis=-1)
    return normal, mask, albedo


def write_object(
    folder: Path,
    directions: np.ndarray,
    intensities: np.ndarray,
    height: int = 64,
    width: int = 76,
    normal_gt: bool = True,
) -> Fixture:
    """Render and write one object folder (created) under the given lights."""
    folder.mkdir(parents=True)
    normal, mask, albedo = shape(height, width)
    shading = np.clip(np.einsum("hwc,kc->khw", normal, directions), 0.0, None)
    radiance = albedo[None] * intensities[:, None, None, :] * shading[..., None]
    radiance *= WHITE / radiance.max()
    names = [f"{k + 1:03d}.png" for k in range(len(directions))]
    for name, image in zip(names, radiance):
        assert cv2.imwrite(str(folder / name), np.rint(image[..., ::-1]).astype(np.uint16))
    (folder / "filenames.txt").write_text("".join(f"{name}\n" for name in names))
    np.savetxt(folder / "light_directions.txt", directions, fmt="%.6f")
    np.savetxt(folder / "light_intensities.txt", intensities, fmt="%.6f")
    assert cv2.imwrite(str(folder / "mask.png"), np.repeat(mask[..., None] * np.uint8(255), 3, axis=-1))
    if normal_gt:
        scipy.io.savemat(folder / "Normal_gt.mat", {"Normal_gt": normal})
    return Fixture(folder, normal, mask, albedo, directions, intensities, radiance)


def random_intensities(count: int, seed: int, rgb_spread: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> np.ndarray:
    """(count, 3) positive RGB intensities around 1, each channel scaled by ``rgb_spread``."""
    rng = np.random.default_rng(seed)
    return rng.uniform(0.6, 1.4, (count, 3)) * np.asarray(rgb_spread)


def write_diligent(folder: Path, seed: int = 0, rgb_spread: tuple[float, float, float] = (1.0, 1.0, 1.0), **kwargs: object) -> Fixture:
    """A 96-light DiLiGenT object folder (e.g. ``.../ballPNG``), 64×76 by default."""
    return write_object(folder, diligent_directions(), random_intensities(96, seed, rgb_spread), **kwargs)  # type: ignore[arg-type]


def write_diligent_pi(folder: Path, seed: int = 0, size: int = 48, normal_gt: bool = True) -> Fixture:
    """A 100-light DiLiGenT-Π object folder of square size×size images."""
    return write_object(folder, pi_directions(), random_intensities(100, seed), size, size, normal_gt)
