"""Analytic surfaces with exact normals and depth, for tests and ``benchmarks/integrate.py``: a sphere
(orthographic or seen through a pinhole camera) and two planes at different heights joined by a step
the normals do not show.

Frames as in ``pstoolkit.surface.base``: x right, y up, z towards the camera; pixel centres at
integers, orthographic x = u − (W−1)/2, y = (H−1)/2 − v.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from pstoolkit.surface.base import Camera


class Synthetic(NamedTuple):
    """``normal`` (H, W, 3) unit normals, zero outside ``mask`` (H, W) bool; ``depth`` (H, W) the true
    z (NaN outside the mask): pixels when ``camera`` is None, else z = −d in the camera's units."""

    normal: np.ndarray
    depth: np.ndarray
    mask: np.ndarray
    camera: Camera | None = None


def sphere(size: int, radius: float) -> Synthetic:
    """An orthographic hemisphere of ``radius`` pixels centred in a ``size``² image; the mask is the
    pixels whose centre lies inside its outline (the rim pixels are nearly grazing)."""
    v, u = np.mgrid[0:size, 0:size].astype(np.float64)
    x, y = u - (size - 1) / 2, (size - 1) / 2 - v
    mask = x**2 + y**2 < radius**2
    z = np.sqrt(np.clip(radius**2 - x**2 - y**2, 0.0, None))
    normal = np.where(mask[..., None], np.stack([x, y, z], axis=-1) / radius, 0.0)
    return Synthetic(normal, np.where(mask, z, np.nan), mask)


def perspective_sphere(size: int, focal: float, distance: float, radius: float) -> Synthetic:
    """A sphere of ``radius`` whose centre lies ``distance`` in front of a pinhole camera on its axis,
    rendered at ``size``² pixels with focal length ``focal`` pixels and the principal point at the
    image centre; units are those of ``distance`` and ``radius``. The mask is the pixels whose ray
    hits the sphere."""
    camera = Camera(fx=focal, fy=focal, cx=(size - 1) / 2, cy=(size - 1) / 2)
    rays = camera.rays((size, size))
    centre = np.array([0.0, 0.0, -distance])
    # |t·r − C|² = R² with r·C = distance (r_z = −1): the nearer root is the visible point
    rr = np.sum(rays**2, axis=-1)
    disc = distance**2 - rr * (distance**2 - radius**2)
    mask = disc > 0
    t = (distance - np.sqrt(np.clip(disc, 0.0, None))) / rr
    point = rays * t[..., None]
    normal = np.where(mask[..., None], (point - centre) / radius, 0.0)
    return Synthetic(normal, np.where(mask, -t, np.nan), mask, camera)


def two_planes(size: int, jump: float, lip: float, width: int = 2) -> Synthetic:
    """Two flat planes side by side, the right one ``jump`` pixels nearer, meeting at a step down the
    lower part of the image (rows from 3/8 of the height down; the step's foot lies between columns
    size/2 − 1 and size/2). Every normal on the planes is (0, 0, 1).

    The step is an occluding contour: its top edge is a rounded lip ``lip`` pixels high and ``width``
    pixels wide (a quarter ellipse, vertical at its foot, so its normals show it) standing on a sheer
    cliff of ``jump − lip`` that no normal shows. The planes' true difference reaches the normals all
    the same, through a path round the top: a horizontal slit (rows 1/4 to 3/8, columns 1/8 to 7/8,
    outside the mask) separates the planes from a top band over which the height rises smoothly from
    0 to ``jump`` (a half cosine between columns 1/4 and 3/4), and the band meets each plane beyond
    the slit's ends. Least squares weighs the step's normals against the path and spreads the
    difference over both; an integrator that cuts the step along the cliff takes it from the path."""
    v, u = np.mgrid[0:size, 0:size].astype(np.float64)
    lo, hi = size / 4, 3 * size / 4
    t = np.clip((u - lo) / (hi - lo), 0.0, 1.0)
    ramp = jump * 0.5 * (1 - np.cos(np.pi * t))
    ramp_slope = np.where((u > lo) & (u < hi), jump * np.pi / (2 * (hi - lo)) * np.sin(np.pi * t), 0.0)
    band = v < size / 4
    e = u - (size / 2 - 0.5)  # distance from the step's foot
    s = np.clip(e / width, 0.0, 1.0)
    rise = np.sqrt(np.clip(1 - (1 - s) ** 2, 1e-12, None))
    planes = np.where(e > 0, jump - lip + lip * rise, 0.0)
    lip_slope = np.where((e > 0) & (e < width), lip * (1 - s) / (width * rise), 0.0)
    mask = np.ones((size, size), dtype=bool)
    mask[size // 4 : (3 * size) // 8, size // 8 : (7 * size) // 8] = False
    gradient = np.where(band, ramp_slope, lip_slope)  # ∂z/∂u; the normal is ∝ (−∂z/∂u, ∂z/∂v, 1)
    normal = np.stack([-gradient, np.zeros_like(u), np.ones_like(u)], axis=-1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    normal[~mask] = 0.0
    return Synthetic(normal, np.where(mask, np.where(band, ramp, planes), np.nan), mask)


def step_jump(depth: np.ndarray, size: int, width: int = 2) -> float:
    """The height difference between the two planes of ``two_planes(size, …, width=width)`` in a
    surface's ``depth``: the median of the right plane minus the median of the left one, over the
    rows below the slit and away from the step and the image's sides (two columns clear of the
    step's foot and of its lip)."""
    rows = slice((3 * size) // 8, size)
    right = depth[rows, size // 2 + width + 2 : (7 * size) // 8]
    left = depth[rows, size // 8 : size // 2 - 2]
    return float(np.nanmedian(right) - np.nanmedian(left))
