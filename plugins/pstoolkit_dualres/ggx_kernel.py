"""The GGX lobe of ``pstoolkit.optics.brdf.GGX.shade`` as numba functions, the one copy both compiled
passes of dualres (``frame_kernel``, ``event_kernel``) inline: the half vector of a light sample
(``ggx_half``), a pixel's own terms (``ggx_pixel``) and the specular factor E = D·V·[n·l]₊ with its
hand-derived derivatives (``ggx_specular``). ``tests/solvers/dualres/test_ggx_kernel.py`` holds the
other copies to it: the torch BRDF (autograd), the simulator's closed form and the viewer's
JavaScript shader.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from pstoolkit.optics.brdf import HALF_EPS, MIN_ROUGHNESS

INV_PI = 1.0 / math.pi


@numba.njit(cache=True, nogil=True, inline="always")
def ggx_half(lx: float, ly: float, lz: float, view: np.ndarray) -> tuple:
    """The half vector of a light direction and the (3,) float64 ``view`` and the HALF_EPS share of
    |l + v|², as ``GGX.shade`` forms them: in float64, returned as float32."""
    sx, sy, sz = np.float64(lx) + view[0], np.float64(ly) + view[1], np.float64(lz) + view[2]
    ss = sx * sx + sy * sy + sz * sz + HALF_EPS
    norm = math.sqrt(ss)
    return np.float32(sx / norm), np.float32(sy / norm), np.float32(sz / norm), np.float32(HALF_EPS / ss)


@numba.njit(cache=True, nogil=True, inline="always")
def ggx_pixel(nx: float, ny: float, nz: float, roughness: float, vx: float, vy: float, vz: float) -> tuple:
    """A pixel's own terms of ``GGX.shade``: α², k, the view term b = n·v (1 − k) + k of V, the clamped
    n·v and roughness r, and 1 or 0 for whether n·v and the roughness pass their clamps' gradient
    (torch's clamp passes it where the input reaches the bound)."""
    zero, one = np.float32(0.0), np.float32(1.0)
    nv_raw = nx * vx + ny * vy + nz * vz
    nv = max(nv_raw, zero)
    r = max(roughness, np.float32(MIN_ROUGHNESS))
    k = (r + one) * (r + one) / np.float32(8.0)
    return (r * r * r * r, k, nv * (one - k) + k, nv, r, one if nv_raw >= zero else zero,
            one if roughness >= np.float32(MIN_ROUGHNESS) else zero)


@numba.njit(cache=True, nogil=True, inline="always")
def ggx_specular(nx: float, ny: float, nz: float, nl: float, lx: float, ly: float, lz: float, hx: float, hy: float,
                 hz: float, he: float, vx: float, vy: float, vz: float, alpha2: float, k: float, b: float, nv: float,
                 r: float, nv_passes: float, r_passes: float) -> tuple:
    """``GGX.shade``'s specular factor E = D·V·[n·l]₊ of one light sample at a normal n with the
    clamped n·l = ``nl``, light l, half vector h with ``he`` (``ggx_half``) and the pixel's terms of
    ``ggx_pixel``, and its hand-derived derivatives: (E, dE/dn x, y, z, dE/dr). The |n × h|² form of
    1 − (n·h)² is the BRDF's."""
    one = np.float32(1.0)
    nh = nx * hx + ny * hy + nz * hz
    cx = ny * hz - nz * hy
    cy = nz * hx - nx * hz
    cz = nx * hy - ny * hx
    q = cx * cx + cy * cy + cz * cz + he + nh * nh * alpha2
    d = alpha2 * np.float32(INV_PI) / (q * q)
    a = nl * (one - k) + k
    vis = one / (np.float32(4.0) * a * b)
    e = d * vis * nl
    # dE/dn = E·(−2/q·dq/dn − (1−k)/a·l − (1−k)/b·v) + D·V·l, dq/dn = 2 h × (n × h) + 2 n·h α² h
    tq = np.float32(-4.0) * e / q
    qx = (hy * cz - hz * cy) + nh * alpha2 * hx
    qy = (hz * cx - hx * cz) + nh * alpha2 * hy
    qz = (hx * cy - hy * cx) + nh * alpha2 * hz
    tl = d * vis - e * (one - k) / a
    tv = -e * (one - k) / b * nv_passes
    dr = e * ((one / alpha2 - np.float32(2.0) * nh * nh / q) * np.float32(4.0) * r * r * r
              - ((one - nl) / a + (one - nv) / b) * (r + one) / np.float32(4.0)) * r_passes
    return e, tq * qx + tl * lx + tv * vx, tq * qy + tl * ly + tv * vy, tq * qz + tl * lz + tv * vz, dr
