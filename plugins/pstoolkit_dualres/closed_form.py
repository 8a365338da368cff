"""Closed-form initial normal and albedo from the long exposures (DualResPS eq. 14, 16; supplement
§1 and Table 1).

A Lambertian pixel sees A_j = ρ · l*_j(x; n) · n in window j, with the equivalent light
l*_j = ∫ m_c(x, t)·[l(t)·n > 0]·l(t) dt: the cast-shadow mask m_c from the events and the
attached-shadow clamp, which depends on the normal sought. The normal is found by fixed-point
iteration (``fixed_point``) from the clamp of n = (0, 0, 1): solve the 3×3 system with the lights of the current
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

import cv2
import numpy as np
from torch import Tensor

from pstoolkit import GREY_WEIGHTS, LightModel
from pstoolkit._shared import devices
from pstoolkit._shared.vectors import unit
from pstoolkit.optics.equivalent import sample_times
from pstoolkit_dualres.closed_form_device import device_fixed_point
from pstoolkit_dualres.fixed_point import fixed_point

# Gaussian widths (pixels) of the normalised convolution that fills pixels from their neighbours.
FILL_SIGMAS = (1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0)

Visibility = Callable[[np.ndarray, np.ndarray], np.ndarray | Tensor]
"""``visibility(t_us (T,), pixel (P,)) -> (T, P) bool``: 1 − m_c at frame pixels (flat indices); a
tensor on the device where the fixed point runs there (``closed_form_device``)."""


@dataclass
class ClosedFormStart:
    """``normal`` (H, W, 3) unit (zero outside the mask), ``albedo`` (H, W, 3), ``effective`` (H, W)
    int number of effective lights, ``iterations`` done."""

    normal: np.ndarray
    albedo: np.ndarray
    effective: np.ndarray
    iterations: int

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
