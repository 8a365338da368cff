"""Orthographic normal integration: the height map whose gradients best match a normal map.

With x right, y up, z towards the camera and image row v growing downwards, a surface of height h(u, v)
towards the camera (in pixels) has the normal ∝ (−∂h/∂u, ∂h/∂v, 1), so ∂h/∂u = −n_x/n_z and
∂h/∂v = n_y/n_z. ``integrate_normals`` solves the least-squares (screened Poisson) problem over
the mask: one equation h(u+1, v) − h(u, v) = ½(p(u, v) + p(u+1, v)) per pair of horizontal
neighbours inside the mask, likewise vertically, each weighted by the pair's mean n_z (a grazing
normal's slope is the least certain), plus a weak pull of every height towards zero that fixes the
free offset of each connected part. A depth step the normals cannot see (an occluding contour) comes
out as the steepest slope the clamped gradients allow, spread over the pixels beside it.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

# Smallest n_z used for a slope: at most 1/MIN_NZ pixels of height per pixel.
MIN_NZ = 0.05
# Weight of the pull towards height 0 against a unit-weight gradient equation: fixes each connected
# part's offset without bending it.
SCREEN = 1e-6


def surface_gradients(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(∂h/∂u, ∂h/∂v, weight) (H, W) each, from unit normals (H, W, 3); n_z is clamped to ``MIN_NZ``
    and the weight is the clamped n_z."""
    nz = np.maximum(np.asarray(normal[..., 2], dtype=np.float64), MIN_NZ)
    return -normal[..., 0] / nz, normal[..., 1] / nz, nz


def integrate_normals(normal: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(H, W) float64 height towards the camera in pixels, 0 outside ``mask`` (H, W) bool, from unit
    normals (H, W, 3) in the camera frame; each connected part of the mask has mean height near 0.
    Raises ValueError on mismatched shapes."""
    mask = np.asarray(mask, dtype=bool)
    if normal.shape != (*mask.shape, 3):
        raise ValueError(f"normal {normal.shape} and mask {mask.shape} disagree")
    height, width = mask.shape
    n = int(mask.sum())
    out = np.zeros((height, width))
    if n == 0:
        return out
    index = np.full((height, width), -1, dtype=np.int64)
    index[mask] = np.arange(n)
    du, dv, weight = surface_gradients(np.asarray(normal, dtype=np.float64))
    rows: list[np.ndarray] = []
    cols: list[np.ndarray] = []
    rhs: list[np.ndarray] = []
    wts: list[np.ndarray] = []
    for grad, axis in ((du, 1), (dv, 0)):
        lo = (slice(None), slice(None, -1)) if axis == 1 else (slice(None, -1), slice(None))
        hi = (slice(None), slice(1, None)) if axis == 1 else (slice(1, None), slice(None))
        both = mask[lo] & mask[hi]
        rows.append(index[lo][both])
        cols.append(index[hi][both])
        rhs.append(0.5 * (grad[lo][both] + grad[hi][both]))
        wts.append(0.5 * (weight[lo][both] + weight[hi][both]))
    first, second = np.concatenate(rows), np.concatenate(cols)
    w = np.concatenate(wts)
    m = first.size
    equation = np.arange(m)
    # each row: h[second] − h[first] = rhs, scaled by its weight
    a = sp.csr_matrix(
        (np.concatenate([w, -w]), (np.concatenate([equation, equation]), np.concatenate([second, first]))), shape=(m, n)
    )
    b = w * np.concatenate(rhs)
    normal_matrix = (a.T @ a + SCREEN * sp.identity(n)).tocsc()
    out[mask] = spla.spsolve(normal_matrix, a.T @ b)
    return out
