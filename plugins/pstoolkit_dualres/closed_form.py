"""Closed-form initial normal and albedo from the long exposures (DualResPS eq. 14, 16; supplement
§1 and Table 1).

A Lambertian pixel sees A_j = ρ · l*_j(x; n) · n in window j, with the equivalent light
l*_j = ∫ m_c(x, t)·[l(t)·n > 0]·l(t) dt: the cast-shadow mask m_c from the events and the
attached-shadow clamp, which depends on the normal sought. The normal is found by fixed-point
iteration from the clamp of n = (0, 0, 1): solve the 3×3 system with the lights of the current
normal, recompute the lights with the clamp of the new normal, repeat while any pixel's normal
still moves. This is Newton's method on F_j(b) = ∫ [l·b]₊ dt − A_j (b = ρn), whose Jacobian is
exactly the clamped equivalent light. Work is on grey (Rec. 601) frames and lights; the RGB
albedo is then fitted per channel by least squares on the shading.

A window's light is *effective* when its length is at least ``EFFECTIVE_SHARE`` of the unshadowed,
unclamped light of that window. Table 1: with three effective lights the normal and albedo are the
closed form. With fewer, the normal is interpolated — from the super pixels (their normals from
events alone, ``eventnormal``, bilinearly interpolated to frame pixels) where the adjacent super
pixels have one, else from the frame pixels with three lights (normalised Gaussian fill); with two
lights only the one free direction comes from it: the interpolated normal is projected onto the
plane of normals the two frames' ratio allows. The albedo is fitted from the effective frames (the
events cannot tell it, albedo invariance), or interpolated from frame pixels where there are none.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from pstoolkit import GREY_WEIGHTS, LightModel
from pstoolkit._shared import devices
from pstoolkit._shared.vectors import unit
from pstoolkit.optics.equivalent import equivalent_lights, sample_times

EFFECTIVE_SHARE = 0.01
# A pixel whose normal turned by less than 0.01° in an iteration has settled.
MOVED_COS = float(np.cos(np.radians(0.01)))
# Gaussian widths (pixels) of the normalised convolution that fills pixels from their neighbours.
FILL_SIGMAS = (1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0)

Visibility = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""``visibility(t_us (T,), pixel (P,)) -> (T, P) bool``: 1 − m_c at frame pixels (flat indices)."""


@dataclass
class ClosedFormStart:
    """``normal`` (H, W, 3) unit (zero outside the mask), ``albedo`` (H, W, 3), ``effective`` (H, W)
    int number of effective lights, ``iterations`` done."""

    normal: np.ndarray
    albedo: np.ndarray
    effective: np.ndarray
    iterations: int


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


def fill(values: np.ndarray, known: np.ndarray, region: np.ndarray) -> np.ndarray:
    """Values (H, W, C) at ``region`` pixels outside ``known`` from known neighbours: normalised
    Gaussian convolution at growing widths until every such pixel has a neighbour."""
    out = values.copy()
    todo = region & ~known
    weight = known.astype(np.float32)
    data = (values * weight[..., None]).astype(np.float32)
    for sigma in FILL_SIGMAS:
        if not todo.any():
            break
        num = cv2.GaussianBlur(data, (0, 0), sigma, borderType=cv2.BORDER_REPLICATE).reshape(values.shape)
        den = cv2.GaussianBlur(weight, (0, 0), sigma, borderType=cv2.BORDER_REPLICATE)
        ready = todo & (den > 1e-4)
        out[ready] = num[ready] / den[ready][:, None]
        todo &= ~ready
    return out


def closed_form(
    frames: np.ndarray,
    windows_us: np.ndarray,
    mask: np.ndarray,
    light: LightModel,
    *,
    visibility: Visibility | None,
    iterations: int,
    n_samples: int,
    super_normal: np.ndarray | None = None,
    base: ClosedFormStart | None = None,
    device: str = "cpu",
) -> ClosedFormStart:
    """Initial normal and albedo maps inside ``mask`` from the long exposures (see the module docstring).

    Parameters
    ----------
    frames
        (J, H, W, 3) frame values, saturation units, one per distinct window of the period.
    windows_us
        (J, 2) the windows [t0, t1], µs on the light's clock.
    mask
        (H, W) bool, the pixels solved.
    light
        The directional light model.
    visibility
        ``visibility(t_us (T,), pixel (P,)) -> (T, P) bool``, 1 − m_c at frame pixels (flat indices), or
        None (no cast-shadow mask).
    iterations
        Most fixed-point iterations of the attached-shadow clamp (at least 1 is done).
    n_samples
        Midpoint-rule samples per window for the equivalent lights.
    super_normal
        (H, W, 3) the normals of the super pixels from their events, interpolated to the frame pixels
        (zero where unknown), or None; where known they fill the pixels with fewer than three
        effective lights.
    base
        An earlier start over a larger mask whose pixels outside ``mask`` stand as they are (a cast-
        shadow mask that changes only the pixels of ``mask``): their normals with three effective
        lights and their albedos with one feed the fills here, as their own solve would. None: the
        pixels outside ``mask`` are unknown.
    device
        Where the fixed-point iteration runs: "cpu" with numpy (``fixed_point``), or a torch device
        (``closed_form_device.device_fixed_point``: the same to rounding). The fills stay on the host.

    Returns
    -------
    ClosedFormStart
        Normal, albedo and number of effective lights per pixel, zero outside ``mask``.
    """
    n_windows, height, width, _ = frames.shape
    pixels = np.flatnonzero(mask.ravel())
    rgb = frames.reshape(n_windows, -1, 3)[:, pixels]
    grey = rgb @ np.asarray(GREY_WEIGHTS)
    # m_c does not depend on the normal: look it up once for all iterations
    masks = None if visibility is None else [visibility(sample_times(t0, t1, n_samples), pixels) for t0, t1 in windows_us]
    if devices.on_host(device):
        point = fixed_point(light, windows_us, grey, masks, iterations=iterations, n_samples=n_samples)
    else:
        from pstoolkit_dualres.closed_form_device import device_fixed_point  # deferred: it builds on this module

        point = device_fixed_point(light, windows_us, grey, masks, iterations=iterations, n_samples=n_samples, device=device)
    normal, effective, solved, lights = point.normal, point.effective, point.solved, point.lights
    full = solved & (effective.sum(axis=0) >= 3)
    count = effective.sum(axis=0)
    normal_map = np.zeros((height * width, 3))
    known = np.zeros(height * width, dtype=bool)
    outside = np.zeros(height * width, dtype=bool) if base is None else ~mask.ravel()
    if base is not None:
        held = outside & (base.effective.ravel() >= 3)
        normal_map[held] = base.normal.reshape(-1, 3)[held]
        known[held] = True
    normal_map[pixels[full]] = normal[full]
    normal_map = normal_map.reshape(height, width, 3)
    known[pixels[full]] = True
    filled = unit(fill(normal_map, known.reshape(height, width), mask)).reshape(-1, 3)[pixels]
    if super_normal is not None:
        # The super pixels' own estimate beats a fill from the nearest frame pixels with three
        # lights, which may lie far inside: so it does on the rim of a simulated sphere, at the pixels
        # with two effective lights (measured in docs/dualres-tuning.md, "Closed-form start: measured
        # choices").
        from_events = super_normal.reshape(-1, 3)[pixels]
        filled = np.where(np.linalg.norm(from_events, axis=1, keepdims=True) > 0.5, from_events, filled)
    normal = np.where(full[:, None], normal, filled)
    two = ~full & (count == 2)
    normal[two] = _two_light_normal(grey[:, two], lights.grey_at(two), effective[:, two], normal[two])
    normal[:, 2] = np.maximum(normal[:, 2], 0.0)
    normal = unit(normal)
    albedo = lights.albedo(rgb, effective, normal)
    albedo_map = np.zeros((height * width, 3))
    has_light = np.zeros(height * width, dtype=bool)
    if base is not None:
        lit = outside & (base.effective.ravel() >= 1)
        albedo_map[lit] = base.albedo.reshape(-1, 3)[lit]
        has_light[lit] = True
    albedo_map[pixels] = albedo
    has_light[pixels[count >= 1]] = True
    albedo_map = fill(albedo_map.reshape(height, width, 3), has_light.reshape(height, width), mask)
    normal_out = np.zeros((height * width, 3))
    normal_out[pixels] = normal
    effective_map = np.zeros(height * width, dtype=np.int64)
    effective_map[pixels] = count
    return ClosedFormStart(
        normal=normal_out.reshape(height, width, 3).astype(np.float32),
        albedo=(albedo_map * mask[..., None]).astype(np.float32),
        effective=effective_map.reshape(height, width),
        iterations=point.iterations,
    )


def _two_light_normal(grey: np.ndarray, lights: np.ndarray, effective: np.ndarray, guess: np.ndarray) -> np.ndarray:
    """Normals that satisfy the ratio of the two effective frames, (A_a l_b − A_b l_a)·n = 0, closest
    to ``guess`` (the interpolated normal): its projection onto that plane."""
    order = np.argsort(~effective, axis=0, kind="stable")[:2]  # the two effective windows
    cols = np.arange(grey.shape[1])
    a, b = order
    plane = grey[a, cols][:, None] * lights[b, cols] - grey[b, cols][:, None] * lights[a, cols]
    plane = unit(plane)
    projected = guess - np.einsum("px,px->p", guess, plane)[:, None] * plane
    return np.where(np.linalg.norm(projected, axis=1, keepdims=True) > 1e-6, unit(projected), guess)


def _albedo(rgb: np.ndarray, lights: np.ndarray, effective: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """ρ_c = Σ_j A_jc s_jc / Σ_j s_jc² over the effective windows, s_jc = l*_jc·n (least squares)."""
    shading = np.einsum("jpcx,px->jpc", lights, normal) * effective[..., None]
    num = np.einsum("jpc,jpc->pc", rgb, shading)
    den = np.einsum("jpc,jpc->pc", shading, shading)
    return np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
