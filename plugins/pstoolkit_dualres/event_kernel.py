"""The event term of eq. 25 as one compiled pass, for the built-in ``ggx`` and ``lambertian`` BRDFs
(``fused_event_loss``).

Through torch, each pair renders its super pixel twice (now and at the reference time) through every
operation of the BRDF on (E, F, 3) intermediates, and the backward scatters the taps' gradients with
``index_put_``, which made the pairs a step can afford few. Here each pair is rendered in registers:
per tap the GGX sample of ``ggx_kernel`` (the same formulas of ``pstoolkit.optics.brdf.GGX.shade``
and its hand-derived derivatives), the two grey sums, the log residual, and the taps' gradients,
which are then added into the pixels in pair order (the result does not depend on the thread count).
Tests compare value and gradients with torch's autograd of ``superpixel_grey`` and ``event_loss``.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from numba import prange
from torch import Tensor

from pstoolkit_dualres.frame_kernel import float32_array, ggx_maps
from pstoolkit_dualres.ggx_kernel import ggx_half, ggx_pixel, ggx_specular
from pstoolkit_dualres.problem import EventTerms
from pstoolkit_dualres.reflectance import INDIRECT, FitModel

# Pairs a thread takes at once (its scratch is allocated once per block).
PAIR_BLOCK = 256


# Fused multiply-adds only: with every fast-math flag the same solve gave different last bits from
# run to run on one machine (the determinism test failed about one process in three).
@numba.njit(cache=True, parallel=True, nogil=True, error_model="numpy", fastmath={"contract"})
def _event_pass(normal: np.ndarray, albedo: np.ndarray, f0: np.ndarray, roughness: np.ndarray, taps: np.ndarray,
                pairs: np.ndarray, weight_now: np.ndarray, weight_ref: np.ndarray, light_now: np.ndarray,
                light_ref: np.ndarray, grey_now: np.ndarray, grey_ref: np.ndarray, target: np.ndarray, weight: np.ndarray,
                area: np.ndarray, indirect: np.ndarray, view: np.ndarray, eps: float, huber: float, scale: float,
                gradient: bool, loss: np.ndarray, contribution: np.ndarray) -> None:
    """Per pair b (event pair ``pairs[b]``): ``loss[b]`` its weighted ``robust_square`` of the log
    residual (``huber`` δ, 0: the square) times ``scale``, and (``gradient``) ``contribution[b, f]``
    the derivatives of that with respect to tap f's normal (0–2), albedo (3–5), F0 (6–8), roughness
    (9) and indirect light (10).

    ``normal``, ``albedo``, ``f0`` (P, 3) float32, ``roughness`` (P,), ``taps`` (B, F) pixel indices;
    of all the pairs: ``weight_now``/``weight_ref`` (E, F) area × lit share of each tap now and at the
    reference time, ``light_now``/``light_ref`` (E, 3) unit light directions, ``grey_now``/``grey_ref``
    (E, 3) intensity × grey weight per channel, ``target``/``weight`` (E,), ``area`` (E, F) each tap's
    area share without the mask and ``indirect`` (P,) the indirect light b, or both (0, 0) / (0,)
    without one (a tap then adds area·b·ρ·grey, shadowed or not); ``view`` (3,) float64.

    Each tap is shaded once: its grey value is summed and the derivatives of that value (normal, [n·l]₊,
    the specular factor, roughness) kept in a scratch until the residual is known. Pairs go in blocks
    of ``PAIR_BLOCK`` so that the scratch is allocated once per block (a layout with the innermost
    loop over a block's pairs, for the compiler to vectorise, was half as fast: its taps are gathers)."""
    count, fan = taps.shape
    ambient = indirect.shape[0] > 0
    vx, vy, vz = np.float32(view[0]), np.float32(view[1]), np.float32(view[2])
    zero = np.float32(0.0)
    for block in prange((count + PAIR_BLOCK - 1) // PAIR_BLOCK):
        # per time and tap: the grey value's derivatives by n (0–2), ρ_c / g_c (3), F0_c / g_c (4), r (5), b (6)
        parts = np.zeros((2, fan, 7), dtype=np.float32)
        sums = np.zeros(2, dtype=np.float32)
        for b in range(block * PAIR_BLOCK, min((block + 1) * PAIR_BLOCK, count)):
            e = pairs[b]
            for t in range(2):
                tap_weight, light, grey = (weight_now, light_now, grey_now) if t == 0 else (weight_ref, light_ref, grey_ref)
                lx, ly, lz = light[e, 0], light[e, 1], light[e, 2]
                hx, hy, hz, he = ggx_half(lx, ly, lz, view)
                g0, g1, g2 = grey[e, 0], grey[e, 1], grey[e, 2]
                total = zero
                for f in range(fan):
                    for x in range(7):
                        parts[t, f, x] = zero
                    w = tap_weight[e, f]
                    i = taps[b, f]
                    rho = g0 * albedo[i, 0] + g1 * albedo[i, 1] + g2 * albedo[i, 2]
                    if ambient:
                        # the indirect light reaches the tap's whole area, in a cast shadow too
                        a = area[e, f]
                        total += a * indirect[i] * rho
                        if gradient:
                            parts[t, f, 3] = a * indirect[i]
                            parts[t, f, 6] = a * rho
                    nx, ny, nz = normal[i, 0], normal[i, 1], normal[i, 2]
                    nl = nx * lx + ny * ly + nz * lz
                    # below the horizon a tap renders 0 with a zero gradient (torch's clamp passes it at 0)
                    if w == zero or nl < zero:
                        continue
                    alpha2, k, view_term, nv, r, nv_passes, r_passes = ggx_pixel(nx, ny, nz, roughness[i], vx, vy, vz)
                    spec, ex, ey, ez, er = ggx_specular(nx, ny, nz, nl, lx, ly, lz, hx, hy, hz, he, vx, vy, vz, alpha2, k,
                                                        view_term, nv, r, nv_passes, r_passes)
                    fre = g0 * f0[i, 0] + g1 * f0[i, 1] + g2 * f0[i, 2]
                    total += w * (rho * nl + fre * spec)
                    if not gradient:
                        continue
                    parts[t, f, 0] = w * (rho * lx + fre * ex)
                    parts[t, f, 1] = w * (rho * ly + fre * ey)
                    parts[t, f, 2] = w * (rho * lz + fre * ez)
                    parts[t, f, 3] += w * nl
                    parts[t, f, 4] = w * spec
                    parts[t, f, 5] = w * fre * er
                sums[t] = total
            residual = math.log(sums[0] + eps) - math.log(sums[1] + eps) - target[e]
            # the Huber form of losses.robust_square: the square within δ, its tangent beyond
            clipped = residual if huber <= 0.0 or abs(residual) <= huber else math.copysign(huber, residual)
            loss[b] = scale * weight[e] * clipped * (np.float32(2.0) * residual - clipped)
            if not gradient:
                continue
            # d loss / d grey now and at the reference
            d_now = np.float32(2.0) * scale * weight[e] * clipped / (sums[0] + eps)
            d_ref = -np.float32(2.0) * scale * weight[e] * clipped / (sums[1] + eps)
            for f in range(fan):
                for x in range(3):
                    contribution[b, f, x] = d_now * parts[0, f, x] + d_ref * parts[1, f, x]
                for c in range(3):
                    contribution[b, f, 3 + c] = d_now * grey_now[e, c] * parts[0, f, 3] + d_ref * grey_ref[e, c] * parts[1, f, 3]
                    contribution[b, f, 6 + c] = d_now * grey_now[e, c] * parts[0, f, 4] + d_ref * grey_ref[e, c] * parts[1, f, 4]
                contribution[b, f, 9] = d_now * parts[0, f, 5] + d_ref * parts[1, f, 5]
                contribution[b, f, 10] = d_now * parts[0, f, 6] + d_ref * parts[1, f, 6]


@numba.njit(cache=True, nogil=True)
def _add_taps(contribution: np.ndarray, taps: np.ndarray, out: np.ndarray) -> None:
    """``out[taps[e, f]] += contribution[e, f]`` in pair order."""
    pairs, fan = taps.shape
    for e in range(pairs):
        for f in range(fan):
            row = taps[e, f]
            for x in range(11):
                out[row, x] += contribution[e, f, x]


class _FusedEventLoss(torch.autograd.Function):
    @staticmethod
    def forward(ctx, normal: Tensor, albedo: Tensor, f0: Tensor, roughness: Tensor, indirect: Tensor, taps: Tensor,
                pairs: Tensor, events: tuple[Tensor, ...], view: Tensor, eps: float, huber: float) -> Tensor:
        count, fan = taps.shape
        gradient = any(ctx.needs_input_grad[:5])
        taps_np = taps.contiguous().numpy()
        loss = np.empty(count, dtype=np.float32)
        contribution = np.empty((count, fan, 11) if gradient else (0, 0, 11), dtype=np.float32)
        shading = (float32_array(x) for x in (normal, albedo, f0, roughness.reshape(-1)))
        _event_pass(*shading, taps_np, pairs.contiguous().numpy(), *(float32_array(x) for x in events),
                    float32_array(indirect.reshape(-1)), view.detach().double().numpy(), float(eps), float(huber),
                    1.0 / max(count, 1), gradient, loss, contribution)
        if gradient:
            out = np.zeros((normal.shape[0], 11), dtype=np.float32)
            _add_taps(contribution, taps_np, out)
            ctx.grads = torch.from_numpy(out)
        return normal.new_tensor(loss.sum(dtype=np.float64))

    @staticmethod
    def backward(ctx, grad: Tensor):
        g = ctx.grads * grad
        need = ctx.needs_input_grad
        parts = (g[:, 0:3], g[:, 3:6], g[:, 6:9], g[:, 9:10], g[:, 10:11])
        return (*(part if wanted else None for part, wanted in zip(parts, need[:5])), *(None,) * 6)


def fused_event_loss(model: FitModel, normal: Tensor, maps: dict[str, Tensor], taps: Tensor, events: EventTerms, pairs: Tensor,
                     view: Tensor, eps: float, huber: float = 0.0) -> Tensor:
    """``event_loss`` of ``superpixel_grey`` now and at the reference time over the event ``pairs``, in
    one compiled pass, with the gradient with respect to ``normal`` and the maps; only where
    ``frame_kernel.supports(model, normal)``.

    Parameters
    ----------
    model
        A FitModel of the built-in GGX or Lambertian.
    normal
        (P, 3) unit normals.
    maps
        ``albedo`` (P, 3), and for GGX ``f0`` (P, 3) and ``roughness`` (P, 1); ``indirect`` (P, 1) for a
        model with indirect light.
    taps
        (B, F) int64 pixels under each pair's super pixel, indices into ``normal``.
    events
        All the pairs' terms (``problem.EventTerms``): tap weights, lights and grey intensities now
        and at the reference time, targets and confidences; read in place.
    pairs
        (B,) int64 the pairs of the step, indices into ``events``.
    view
        (3,) unit direction to the camera.
    eps
        ε of the log, in irradiance units.
    huber
        δ of ``losses.robust_square`` in log units (0: the plain square).

    Returns
    -------
    Tensor
        The scalar Σ w·ρ_δ(ln((Ĩ_k + ε)/(Ĩ_ref + ε)) − target) / B, differentiable.
    """
    albedo, f0, roughness = ggx_maps(model, normal, maps)
    if model.indirect:
        area, indirect = events.tap_area, maps[INDIRECT.name]
    else:
        area, indirect = events.tap_weight_now.new_zeros((0, 0)), normal.new_zeros((0, 1))
    terms = (events.tap_weight_now, events.tap_weight_ref, events.light_now, events.light_ref, events.grey_now, events.grey_ref,
             events.target, events.weight, area)
    return _FusedEventLoss.apply(normal, albedo, f0, roughness, indirect, taps, pairs, terms, view, eps, huber)
