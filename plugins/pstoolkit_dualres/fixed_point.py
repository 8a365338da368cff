"""The fixed point of the closed form's attached-shadow clamp (``closed_form``; DualResPS eq. 14, 16):
per pixel, the normal b/|b| of b = ρ·n solving the grey windows' values A_j = l*_j(n)·b by least
squares, with the equivalent lights l*_j of the clamp [l(t)·n > 0] (and the cast-shadow mask) of the
normal it solves for, iterated from the clamp of n = (0, 0, 1) while any pixel's normal still moves.
This is Newton's method on F_j(b) = ∫ [l·b]₊ dt − A_j, whose Jacobian is exactly the clamped
equivalent light. ``fixed_point`` is numpy's, on the host; ``closed_form_device`` is its torch copy.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from pstoolkit import GREY_WEIGHTS, LightModel
from pstoolkit._shared.vectors import unit
from pstoolkit.optics.equivalent import equivalent_lights

# A window's light is effective when its length is at least this share of the unshadowed, unclamped
# light of the window (``closed_form``'s module docstring).
EFFECTIVE_SHARE = 0.01
# A pixel whose normal turned by less than 0.01° in an iteration has settled.
MOVED_COS = float(np.cos(np.radians(0.01)))


def window_lights(
    light: LightModel,
    windows_us: np.ndarray,
    n_pixels: int,
    *,
    normals: np.ndarray | None,
    visibility: list[np.ndarray] | None,
    n_samples: int,
) -> np.ndarray:
    """Per-channel equivalent lights of the exposure windows (``equivalent_lights``, eq. 14/16).

    Parameters
    ----------
    light
        The directional light model.
    windows_us
        (J, 2) the windows [t0, t1], µs on the light's clock.
    n_pixels
        Number of pixels P.
    normals
        (n_pixels, 3) unit normals whose attached-shadow clamp applies, or None (no clamp).
    visibility
        Per window, the (n_samples, n_pixels) bool visibility 1 − m_c at its ``sample_times``, or None
        (all visible).
    n_samples
        Midpoint-rule samples per window.

    Returns
    -------
    numpy.ndarray
        (J, n_pixels, 3, 3) float64, axis −2 the RGB channel, axis −1 xyz; the same for every pixel
        without ``normals`` and ``visibility``.
    """
    out = np.empty((len(windows_us), n_pixels, 3, 3))
    for j, (t0, t1) in enumerate(windows_us):
        vis = None if visibility is None else visibility[j]
        lights = equivalent_lights(light, t0, t1, n_samples=n_samples, normals=normals, visibility=vis)
        out[j] = np.broadcast_to(lights.reshape(-1, 3, 3), (n_pixels, 3, 3))
    return out


def _grey(lights: np.ndarray) -> np.ndarray:
    return np.einsum("c,...cx->...x", np.asarray(GREY_WEIGHTS), lights)


def _solve(grey_lights: np.ndarray, grey: np.ndarray, usable: np.ndarray) -> np.ndarray:
    """b = ρ·n per pixel from the (J, P, 3) lights and (J, P) values, least squares over the windows
    where ``usable``; zero where fewer than three usable windows or a singular system."""
    w = usable.astype(np.float64)
    lhs = np.einsum("jp,jpx,jpy->pxy", w, grey_lights, grey_lights)
    rhs = np.einsum("jp,jpx,jp->px", w, grey_lights, grey)
    eig = np.linalg.eigvalsh(lhs)
    ok = (usable.sum(axis=0) >= 3) & (eig[:, 0] > 1e-9 * np.maximum(eig[:, 2], 1e-300))
    b = np.zeros_like(rhs)
    b[ok] = np.linalg.solve(lhs[ok], rhs[ok][..., None])[..., 0]
    return b

@dataclass
class HostLights:
    """The per-pixel equivalent lights ``lights`` (J, P, 3, 3) (``window_lights``) of a fixed point
    solved on the host."""

    lights: np.ndarray

    def grey_at(self, index: np.ndarray) -> np.ndarray:
        """(J, n, 3) the grey lights of the pixels ``index`` (bool (P,) or positions)."""
        return _grey(self.lights)[:, index]

    def albedo(self, rgb: np.ndarray, effective: np.ndarray, normal: np.ndarray) -> np.ndarray:
        """(P, 3) ``_albedo`` of the windows' values ``rgb`` (J, P, 3) with these lights."""
        return _albedo(rgb, self.lights, effective, normal)


@dataclass
class FixedPoint:
    """The fixed point of the attached-shadow clamp (module docstring): ``normal`` (P, 3) unit (the
    start's (0, 0, 1) where never solved), ``effective`` (J, P) bool, ``solved`` (P,) bool: a
    nonzero solve at the last iteration the pixel took, ``iterations`` done, and ``lights``, the
    equivalent lights of the last iteration (``HostLights``, or the device's)."""

    normal: np.ndarray
    effective: np.ndarray
    solved: np.ndarray
    iterations: int
    lights: HostLights | Any


def fixed_point(light: LightModel, windows_us: np.ndarray, grey: np.ndarray, masks: list[np.ndarray] | None, *,
                iterations: int, n_samples: int) -> FixedPoint:
    """The fixed-point iteration of the normals (module docstring) with numpy, from the clamp of
    (0, 0, 1): ``grey`` (J, P) the pixels' grey window values, ``masks`` per window the
    (n_samples, P) visibility at its ``sample_times`` or None; the pixels whose normal still moves
    by 0.01° (``MOVED_COS``) are iterated again, at most ``iterations`` times (at least once)."""
    n_windows, n_pixels = grey.shape
    free = window_lights(light, windows_us, 1, normals=None, visibility=None, n_samples=n_samples)[:, 0]
    free_norm = np.linalg.norm(_grey(free), axis=-1)  # (J,)
    # Start from the clamp of a normal facing the camera: on a simulated sphere the first solve
    # without any clamp falls into wrong fixed points near the rim (measured in docs/dualres-tuning.md,
    # "Closed-form start: measured choices").
    normal = np.tile(np.array([0.0, 0.0, 1.0]), (n_pixels, 1))
    lights = np.empty((n_windows, n_pixels, 3, 3))
    effective = np.zeros((n_windows, n_pixels), dtype=bool)
    solved = np.zeros(n_pixels, dtype=bool)
    # only pixels whose normal still moves are iterated again
    active = np.arange(n_pixels)
    done = 0
    for done in range(1, max(iterations, 1) + 1):  # noqa: B007 -- the count after the loop is the record
        vis = None if masks is None else [m[:, active] for m in masks]
        lights[:, active] = window_lights(light, windows_us, active.size, normals=normal[active], visibility=vis, n_samples=n_samples)
        effective[:, active] = np.linalg.norm(_grey(lights[:, active]), axis=-1) >= EFFECTIVE_SHARE * free_norm[:, None]
        updated = unit(_solve(_grey(lights[:, active]), grey[:, active], effective[:, active]))
        moved = np.any(updated != 0, axis=1)
        solved[active] = moved
        change = np.einsum("px,px->p", updated, normal[active])
        normal[active[moved]] = updated[moved]
        active = active[moved & (change < MOVED_COS)]
        if active.size == 0:
            break
    return FixedPoint(normal, effective, solved, done, HostLights(lights))


def _albedo(rgb: np.ndarray, lights: np.ndarray, effective: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """ρ_c = Σ_j A_jc s_jc / Σ_j s_jc² over the effective windows, s_jc = l*_jc·n (least squares)."""
    shading = np.einsum("jpcx,px->jpc", lights, normal) * effective[..., None]
    num = np.einsum("jpc,jpc->pc", rgb, shading)
    den = np.einsum("jpc,jpc->pc", shading, shading)
    return np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
