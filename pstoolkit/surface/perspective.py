"""Slopes of a normal map for integration, orthographic and perspective, and the depth of an
integrated perspective surface.

Perspective (Durou, Quéau et al., "Normal integration: a survey", the log-depth substitution): the
point of pixel (u, v) at distance d along the axis is P = d·r, r = ((u − cx)/fx, −(v − cy)/fy, −1)
(``Camera.rays``). The normal n is orthogonal to ∂P/∂u = d_u·r + d·(1/fx, 0, 0) and to
∂P/∂v = d_v·r + d·(0, −1/fy, 0), so with ũ = log d and q = −n·r (> 0 for a normal facing the camera)

    ∂ũ/∂u = n_x / (fx·q),        ∂ũ/∂v = −n_y / (fy·q),

linear equations in ũ solved exactly as the orthographic slopes are; d = exp(ũ) follows up to the
scale exp(constant) that normals cannot fix. q/|r| is the cosine between the normal and the pixel's
line of sight, the perspective twin of n_z: it is clamped to ``MIN_NZ`` (a grazing normal gives at
most the slope a cosine of ``MIN_NZ`` gives) and weights each equation. In the orthographic limit
(fx → ∞, d ≈ fx) the equations become those of ``surface_gradients``.
"""

from __future__ import annotations

import numpy as np

from pstoolkit.surface.base import Camera
from pstoolkit.surface.integrate import MIN_NZ, surface_gradients


def slopes(normal: np.ndarray, camera: Camera | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(∂/∂u, ∂/∂v, weight) (H, W) each of the integrated quantity from unit normals (H, W, 3): the
    height in pixels when ``camera`` is None (``surface_gradients``), log-depth through ``camera``
    otherwise (module docstring); the weight is the clamped cosine to the line of sight."""
    if camera is None:
        return surface_gradients(normal)
    rays = camera.rays(normal.shape[:2])
    length = np.linalg.norm(rays, axis=-1)
    q = np.maximum(-np.sum(normal * rays, axis=-1), MIN_NZ * length)
    return normal[..., 0] / (camera.fx * q), -normal[..., 1] / (camera.fy * q), q / length


def depth_of(values: np.ndarray, mask: np.ndarray, camera: Camera | None) -> np.ndarray:
    """(H, W) float64 ``Surface.depth`` from the integrated ``values`` (H, W) over ``mask``, NaN
    outside: the height itself when ``camera`` is None; through ``camera``, z = −d with
    d = f·exp(ũ − median ũ) (f = ``camera.focal``), the scale that puts the mask's median distance at
    f, where a pixel spans one unit (``pstoolkit.surface.base``)."""
    depth = np.full(mask.shape, np.nan)
    if not mask.any():
        return depth
    if camera is None:
        depth[mask] = values[mask]
    else:
        log_d = values[mask]
        depth[mask] = -camera.focal * np.exp(log_d - np.median(log_d))
    return depth
