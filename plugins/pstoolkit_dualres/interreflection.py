"""One diffuse bounce of inter-reflection, predicted from the fitted surface and taken out of the
frames and the events between stages (option ``interreflection`` of ``dualres``; the iteration of
Nayar, Ikeuchi and Kanade, "Shape from interreflections", 1991).

A concavity lit from one side sends light from its lit wall onto the other, most of it while the other
is turned away from the light or in cast shadow: the frames and events there carry light the direct
model cannot explain, and a fit that explains it with direct light alone tilts the facing walls
towards the camera (the relief comes out shallow, its cast shadows short). Given the current normals,
their integrated height, the diffuse albedo and the cast-shadow mask, the irradiance a patch x receives
from the rest of the surface in one diffuse bounce is

    B(x, t) = γ · Σ_y ρ(y) · D(y, t) · cos θ_x · cos θ_y / (π r²) · A_y · V(x, y),

with D(y, t) = [n_y·l(t)]₊ · lit(y, t) the direct irradiance of y per unit light, A_y = 1 / n_z(y) the
area of y's pixel on the surface, V the height field's visibility between x and y, and γ the reflectance
of the capture's albedo scale: the fitted albedo is relative (the frames fix it only up to the light's
intensity), so γ is the one number the fit cannot give — 0 for a renderer without inter-reflection,
about the brightest albedo's reflectance for a real object (more with a specular bounce). The pixel
reflects ρ(x)·B(x, t) more than the direct model predicts. ``remove_bounce`` takes it out: from the
measured frames that light integrated over each frame (``frame_offsets``), and from each event pair's
target the log ratio of the direct share of its super-pixel irradiance at its two ends (``event_offsets``
against ``direct_irradiance``; a pair whose direct share is below ``MIN_DIRECT_SHARE`` at either end says
little of the direct shading and is left out).

The sum runs on a grid of coarse cells (``bounce``: the bounce is smooth at the scale of a pixel), at
``PHASES`` light directions per turn; on a fit that is not on the CPU, its work over the pixels runs on
the fit's device (``bounce_device``).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from pstoolkit import ShadowMask
from pstoolkit._shared import devices
from pstoolkit.events.rule import LOG_EPS
from pstoolkit.optics.lights import LightModel
from pstoolkit.shadows.intervals import grid_times
from pstoolkit.shadows.table_device import DeviceShadowMask
from pstoolkit_dualres.bounce import Bounce, Cells, one_bounce
from pstoolkit_dualres.bounce_device import bounce_there, cell_direct_there, event_offsets_there, frame_offsets_there
from pstoolkit_dualres.forward_model import frame_prediction
from pstoolkit_dualres.losses import event_loss, frame_loss, grid_frame_loss, pair_grey
from pstoolkit_dualres.problem import EventTerms, FrameTerms, Problem
from pstoolkit_dualres.reflectance import FitModel

# Light directions per period the bounce is evaluated at (and interpolated between, cyclically).
PHASES = 96
# Pairs whose direct share of the irradiance is below this at either end are left out.
MIN_DIRECT_SHARE = 0.2
# Event pairs rendered at once for their direct irradiance.
PAIR_CHUNK = 65536


def frame_offsets(frames: FrameTerms, bounce: Bounce, albedo: np.ndarray, t0_us: float, period_us: float) -> np.ndarray:
    """(K·P, 3) ρ(x)·∫ B(x, t)·e(t) dt over each frame's window (γ = 1), in the frames' units: the
    frame samples' weights without the mask (the bounce reaches a pixel in cast shadow too).
    ``albedo`` (P, 3) the fitted diffuse albedo in units of the albedo scale."""
    src = frames.source
    k, p = frames.count, albedo.shape[0]
    if "shared_t" in src:
        assert frames.shared_weight is not None
        weight = frames.shared_weight.detach().cpu().numpy().astype(np.float64)  # (K·S, 3), frame-major
        per_frame = len(weight) // k
        light = np.zeros((k, p, 3))
        for sample, t_us in enumerate(src["shared_t"]):
            light[sample // per_frame] += bounce.everywhere(float(np.mod(t_us - t0_us, period_us))) * weight[sample]
        return (albedo[None] * light).reshape(k * p, 3)
    pixel = src["sample_pixel"]
    group = frames.sample_group.cpu().numpy()
    reflected = albedo[pixel] * bounce.at(np.mod(src["sample_t"] - t0_us, period_us), pixel) * src["sample_weight"]
    return np.stack([np.bincount(group, weights=reflected[:, c], minlength=k * p) for c in range(3)], axis=1)


def event_offsets(events: EventTerms, bounce: Bounce, albedo: np.ndarray, t0_us: float, period_us: float
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(E,) each pair's super-pixel grey irradiance from the bounce (γ = 1) at its later and at its
    earlier time: Σ_taps area × grey(ρ·B), the taps' whole area (no cast shadow removes it)."""
    src = events.source
    taps = events.taps.cpu().numpy()
    area = src["area"]
    fan = taps.shape[1]
    out = []
    for key, grey in (("t_us", events.grey_now), ("t_ref_us", events.grey_ref)):
        phase = np.mod(src[key] - t0_us, period_us)
        grey_np = grey.cpu().numpy().astype(np.float64)
        value = np.zeros(taps.shape[0])
        for first in range(0, taps.shape[0], PAIR_CHUNK):
            part = slice(first, first + PAIR_CHUNK)
            light = bounce.at(np.repeat(phase[part], fan), taps[part].ravel()).reshape(-1, fan, 3)
            value[part] = np.sum(np.sum(albedo[taps[part]] * light * grey_np[part, None, :], axis=-1) * area[part], axis=-1)
        out.append(value)
    return out[0], out[1]


def direct_irradiance(model: FitModel, normal: Tensor, maps: dict[str, Tensor], events: EventTerms, view: Tensor
                      ) -> tuple[np.ndarray, np.ndarray]:
    """(E,) the fit's own super-pixel grey irradiance (``losses.pair_grey``, under the current mask) of
    every pair at its later and at its earlier time, without gradients, ``PAIR_CHUNK`` pairs at a time."""
    count = events.taps.shape[0]
    now, ref = np.zeros(count), np.zeros(count)
    with torch.no_grad():
        for first in range(0, count, PAIR_CHUNK):
            pairs = torch.arange(first, min(first + PAIR_CHUNK, count), device=events.taps.device)
            grey, grey_ref = pair_grey(model, normal, maps, events.taps[pairs], events, pairs, view)
            now[first : first + pairs.numel()] = grey.cpu().numpy()
            ref[first : first + pairs.numel()] = grey_ref.cpu().numpy()
    return now, ref


def remove_bounce(problem: Problem, model: FitModel, normal: Tensor, maps: dict[str, Tensor], height: np.ndarray,
                  shadows: ShadowMask, light: LightModel, t0_us: float, period_us: float, gamma: float) -> dict[str, float]:
    """Take γ times the bounce of the current fit (module docstring) out of ``problem``'s frames and
    event targets, from the measurements as built (so each call replaces the last one's).

    Parameters
    ----------
    problem
        The fit's tensors, with ``shadows`` applied.
    model, normal, maps
        The fitted BRDF (with an RGB diffuse albedo), (P, 3) normals and its maps at the P pixels.
    height
        (H, W) the height of ``normal`` integrated over the P pixels, frame pixels
        (``pstoolkit.shadows.surface_sweep.integrated_height``).
    shadows
        The current cast-shadow mask.
    light
        The capture's light model.
    t0_us, period_us
        Start of the light's period and its length, µs.
    gamma
        γ > 0, the reflectance of the albedo scale.

    Returns
    -------
    dict
        ``bounce_frame_share``: the bounce's share of the measured frames' mean; ``bounce_pairs_dropped``:
        the share of event pairs left out.
    """
    geometry = problem.geometry
    h, w, pixels = geometry.height, geometry.width, geometry.pixels
    normal_np = normal.detach().cpu().numpy().astype(np.float64)
    albedo = maps[model.diffuse].detach().cpu().numpy().astype(np.float64)
    full_normal, full_albedo = np.zeros((h * w, 3)), np.zeros((h * w, 3))
    full_normal[pixels], full_albedo[pixels] = normal_np, albedo
    full_normal, full_albedo = full_normal.reshape(h, w, 3), full_albedo.reshape(h, w, 3)
    mask = np.zeros(h * w, dtype=bool)
    mask[pixels] = True
    mask = mask.reshape(h, w)
    phase = grid_times(period_us, PHASES)
    directions = light.evaluate(t0_us + phase)[0]
    if devices.on_host(problem.device):
        lit = ~shadows.contains_grid(pixels, t0_us + phase) if len(shadows) else np.ones((PHASES, pixels.size), dtype=bool)
        bounce = one_bounce(full_normal, full_albedo, height, mask, lit, directions, phase, period_us)
        offset = gamma * frame_offsets(problem.frames, bounce, albedo, t0_us, period_us)
        bounce_now, bounce_ref = event_offsets(problem.events, bounce, albedo, t0_us, period_us)
    else:
        offset, bounce_now, bounce_ref = _offsets_there(problem, normal, maps[model.diffuse], full_normal, full_albedo, height,
                                                        mask, shadows, directions, phase, t0_us, period_us)
        offset *= gamma
    measured = problem.frames.apply_bounce(offset)
    direct_now, direct_ref = direct_irradiance(model, normal, maps, problem.events, geometry.view)
    share_now = direct_now / np.maximum(direct_now + gamma * bounce_now, 1e-12)
    share_ref = direct_ref / np.maximum(direct_ref + gamma * bounce_ref, 1e-12)
    keep = (share_now >= MIN_DIRECT_SHARE) & (share_ref >= MIN_DIRECT_SHARE)
    shift = np.log(np.maximum(share_now, MIN_DIRECT_SHARE)) - np.log(np.maximum(share_ref, MIN_DIRECT_SHARE))
    problem.events.apply_bounce(shift, keep, gamma * bounce_now, gamma * bounce_ref)
    return {"bounce_frame_share": float(np.mean(offset) / max(float(np.mean(measured)), 1e-12)),
            "bounce_pairs_dropped": float(np.mean(~keep)) if keep.size else 0.0}


def _offsets_there(problem: Problem, normal: Tensor, albedo: Tensor, full_normal: np.ndarray, full_albedo: np.ndarray,
                   height: np.ndarray, mask: np.ndarray, shadows: ShadowMask, directions: np.ndarray, phase_us: np.ndarray,
                   t0_us: float, period_us: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``remove_bounce``'s bounce (γ = 1), its frame offsets and its pairs' irradiance, on the fit's device
    (``bounce_device``): ``normal``/``albedo`` (P, 3) the fit's, ``full_normal``/``full_albedo`` (H, W, 3)
    the same on the frame grid of ``mask``."""
    device = problem.device
    pixels = torch.as_tensor(problem.geometry.pixels, dtype=torch.int64, device=device)
    times = torch.as_tensor(t0_us + phase_us, dtype=torch.float64, device=device)
    lit = ~DeviceShadowMask(shadows, device).contains_grid(pixels, times)
    cells = Cells.of(mask)
    normal64, albedo64 = normal.detach().to(torch.float64), albedo.detach().to(torch.float64)
    direct = cell_direct_there(cells, normal64, lit, directions)
    there = bounce_there(cells, full_normal, full_albedo, height, direct, period_us)
    offset = frame_offsets_there(problem.frames, there, albedo64, t0_us, period_us)
    now, ref = event_offsets_there(problem.events, there, albedo64, t0_us, period_us)
    return offset.cpu().numpy(), now.cpu().numpy(), ref.cpu().numpy()


def unexplained(problem: Problem, model: FitModel, normal: Tensor, maps: dict[str, Tensor], frame_weight: float,
                event_weight: float, huber: float, pairs: np.ndarray) -> float:
    """λ_f·(mean |Ã − A|) + λ_e·(``losses.event_loss``) of the fit against the measurements as built,
    with the bounce ``problem`` holds added to its prediction (the frames' ``FrameTerms.apply_bounce``
    offsets, the pairs' ``bounce_now``/``bounce_ref``): the training loss without its regularisers, over
    the event pairs ``pairs`` (indices, usable under the mask of each fit compared) and with the weights
    the pairs had before ``apply_bounce`` left any out, so that fits with and without a bounce compare."""
    frames, events = problem.frames, problem.events
    with torch.no_grad():
        frame_term = float(grid_frame_loss(model, normal, maps, frames.shared_light, frames.shared_weight, frames.shared_visible,
                                           problem.geometry.view, frames.count, frames.measured, frames.saturated,
                                           energy=frames.energy)) if frames.shared_light is not None else float(
            frame_loss(frame_prediction(model, normal, maps, frames.sample_pixel, frames.sample_group, frames.sample_light,
                                        frames.sample_weight, problem.geometry.view, frames.count * normal.shape[0],
                                        energy=frames.energy), frames.measured, frames.saturated))
    src = events.source
    usable = np.asarray(pairs, dtype=np.int64)
    if usable.size == 0 or event_weight <= 0:
        return frame_weight * frame_term
    direct_now, direct_ref = direct_irradiance(model, normal, maps, events, problem.geometry.view)

    def chosen(values: np.ndarray) -> Tensor:
        return torch.as_tensor(values[usable], dtype=torch.float64)

    event_term = float(event_loss(chosen(direct_now + src.get("bounce_now", 0.0)), chosen(direct_ref + src.get("bounce_ref", 0.0)),
                                  chosen(events.measured_steps()), chosen(events.gated_weight()), LOG_EPS, huber))
    return frame_weight * frame_term + event_weight * event_term
