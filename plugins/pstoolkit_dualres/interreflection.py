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

The sum runs on a grid of at most ``WORK_SIDE`` cells a side (the bounce is smooth at the scale of a
pixel) over neighbours within ``RADIUS_CELLS`` cells, at ``PHASES`` light directions per turn.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
import torch
from numba import prange
from torch import Tensor

from pstoolkit import ShadowMask
from pstoolkit.events.rule import LOG_EPS
from pstoolkit.optics.lights import LightModel
from pstoolkit.shadows.intervals import grid_times
from pstoolkit_dualres.forward_model import frame_prediction
from pstoolkit_dualres.losses import event_loss, frame_loss, grid_frame_loss, pair_grey
from pstoolkit_dualres.problem import EventTerms, FrameTerms, Problem
from pstoolkit_dualres.reflectance import FitModel

# Cells per side of the grid the bounce is summed on: the kernel's cost grows with the cells times
# the neighbours.
WORK_SIDE = 96
# Neighbours within this many cells contribute (a concavity narrower than a third of the frame).
RADIUS_CELLS = 32
# Light directions per period the bounce is evaluated at (and interpolated between, cyclically).
PHASES = 96
# Smallest n_z taken for a patch's area (at most 1/MIN_NZ cells of surface per cell).
MIN_NZ = 0.1
# Pairs whose direct share of the irradiance is below this at either end are left out.
MIN_DIRECT_SHARE = 0.2
# Event pairs rendered at once for their direct irradiance.
PAIR_CHUNK = 65536


@numba.njit(cache=True, parallel=True, nogil=True)
def _bounce(point: np.ndarray, normal: np.ndarray, albedo: np.ndarray, direct: np.ndarray, inside: np.ndarray,
            height: np.ndarray, radius: int, out: np.ndarray) -> None:
    """``out`` (Hc, Wc, T, 3) += the one-bounce sum of the module docstring (γ = 1) at every cell
    inside; ``point``, ``normal`` (Hc, Wc, 3) in cell units, ``albedo`` (Hc, Wc, 3), ``direct``
    (Hc, Wc, T), ``inside`` (Hc, Wc) bool, ``height`` (Hc, Wc) cell units."""
    hc, wc = inside.shape
    t_count = direct.shape[2]
    for v in prange(hc):
        for u in range(wc):
            if not inside[v, u]:
                continue
            px, py, pz = point[v, u, 0], point[v, u, 1], point[v, u, 2]
            nx, ny, nz = normal[v, u, 0], normal[v, u, 1], normal[v, u, 2]
            for dv in range(-radius, radius + 1):
                vy = v + dv
                if vy < 0 or vy >= hc:
                    continue
                for du in range(-radius, radius + 1):
                    uy = u + du
                    if uy < 0 or uy >= wc or (du == 0 and dv == 0) or du * du + dv * dv > radius * radius:
                        continue
                    if not inside[vy, uy]:
                        continue
                    dx, dy, dz = point[vy, uy, 0] - px, point[vy, uy, 1] - py, point[vy, uy, 2] - pz
                    r2 = dx * dx + dy * dy + dz * dz
                    r = math.sqrt(r2)
                    cos_x = (nx * dx + ny * dy + nz * dz) / r
                    cos_y = -(normal[vy, uy, 0] * dx + normal[vy, uy, 1] * dy + normal[vy, uy, 2] * dz) / r
                    if cos_x <= 0.0 or cos_y <= 0.0:
                        continue
                    # the segment between the two patches must pass above the height field
                    steps = max(abs(du), abs(dv))
                    blocked = False
                    for s in range(1, steps):
                        f = s / steps
                        su = int(round(u + f * du))
                        sv = int(round(v + f * dv))
                        if inside[sv, su] and height[sv, su] > pz + f * dz + 0.5:
                            blocked = True
                            break
                    if blocked:
                        continue
                    k = cos_x * cos_y / (math.pi * r2) / max(normal[vy, uy, 2], MIN_NZ)
                    for t in range(t_count):
                        d = direct[vy, uy, t]
                        if d > 0.0:
                            for c in range(3):
                                out[v, u, t, c] += k * albedo[vy, uy, c] * d


def _pool(values: np.ndarray, weight: np.ndarray, stride: int, shape: tuple[int, int]) -> np.ndarray:
    """Weighted mean of ``values`` (H, W, ...) over stride×stride blocks into ``shape`` cells."""
    h, w = weight.shape
    hc, wc = shape
    pad_h, pad_w = hc * stride - h, wc * stride - w
    vals = np.pad(values * weight.reshape(h, w, *([1] * (values.ndim - 2))),
                  [(0, pad_h), (0, pad_w)] + [(0, 0)] * (values.ndim - 2))
    wts = np.pad(weight, [(0, pad_h), (0, pad_w)])
    vals = vals.reshape(hc, stride, wc, stride, *values.shape[2:]).sum(axis=(1, 3))
    wts = wts.reshape(hc, stride, wc, stride).sum(axis=(1, 3))
    return vals / np.maximum(wts, 1e-12).reshape(hc, wc, *([1] * (values.ndim - 2)))


@dataclass
class Bounce:
    """B/γ of the module docstring on the cells it was summed on: ``value`` (T, C, 3) at the phases
    ``phase_us`` (T,) (µs since the phase origin, bin centres of one period ``period_us``), and
    ``cell`` (P,) the cell of each masked frame pixel (the bounce is smooth at the scale of a cell)."""

    value: np.ndarray
    cell: np.ndarray
    phase_us: np.ndarray
    period_us: float

    def _bracket(self, phase_us: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        t = len(self.phase_us)
        pos = np.mod(np.asarray(phase_us, dtype=np.float64) / self.period_us * t - 0.5, t)
        lo = np.floor(pos).astype(np.int64)
        return lo, (lo + 1) % t, pos - lo

    def at(self, phase_us: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """(N, 3) at the pixels ``rows`` (N,) (positions among the P) and phases ``phase_us`` (N,),
        linear in phase, cyclic."""
        lo, hi, frac = self._bracket(phase_us)
        cell = self.cell[rows]
        return self.value[lo, cell] * (1.0 - frac[:, None]) + self.value[hi, cell] * frac[:, None]

    def everywhere(self, phase_us: float) -> np.ndarray:
        """(P, 3) at every masked pixel at one phase."""
        lo, hi, frac = self._bracket(np.array([phase_us]))
        return (self.value[lo[0]] * (1.0 - frac[0]) + self.value[hi[0]] * frac[0])[self.cell]


def one_bounce(normal: np.ndarray, albedo: np.ndarray, height: np.ndarray, mask: np.ndarray, lit: np.ndarray,
               directions: np.ndarray, phase_us: np.ndarray, period_us: float) -> Bounce:
    """The one-bounce irradiance B/γ (module docstring) of a surface.

    Parameters
    ----------
    normal
        (H, W, 3) unit normals (camera frame: x right, y up, z towards the camera).
    albedo
        (H, W, 3) diffuse albedo, relative units.
    height
        (H, W) height towards the camera, frame pixels (``pstoolkit.surface.integrate_normals``).
    mask
        (H, W) bool, the pixels on the object.
    lit
        (T, P) bool, whether each masked pixel (flat order) is out of cast shadow at each phase.
    directions
        (T, 3) unit light directions at the phases ``phase_us`` (T,), grid bin centres of one period.
    period_us
        The light period, µs.

    Returns
    -------
    Bounce
        On a grid of at most ``WORK_SIDE`` cells a side, with the cell of each masked pixel.
    """
    h, w = mask.shape
    stride = max(1, math.ceil(max(h, w) / WORK_SIDE))
    shape = (math.ceil(h / stride), math.ceil(w / stride))
    weight = mask.astype(np.float64)
    pixels = np.flatnonzero(mask)
    t_count = len(directions)
    cell_normal = _pool(normal, weight, stride, shape)
    cell_normal /= np.maximum(np.linalg.norm(cell_normal, axis=-1, keepdims=True), 1e-12)
    cell_albedo = _pool(albedo, weight, stride, shape)
    cell_height = _pool(height, weight, stride, shape) / stride
    # the direct light a phase at a time: no (T, H·W) array at a large capture
    cell_direct = np.zeros((*shape, t_count))
    plane = np.zeros(h * w)
    facing = normal.reshape(-1, 3)[pixels]
    for t in range(t_count):
        plane[pixels] = np.clip(facing @ directions[t], 0.0, None) * lit[t]
        cell_direct[..., t] = _pool(plane.reshape(h, w), weight, stride, shape)
    inside = _pool(weight, np.ones_like(weight), stride, shape) >= 0.5
    v, u = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    point = np.stack([u, -v, cell_height], axis=-1)
    out = np.zeros((*shape, t_count, 3))
    _bounce(point, cell_normal, cell_albedo, cell_direct, inside, cell_height, RADIUS_CELLS, out)
    pv, pu = np.divmod(pixels, w)
    value = np.ascontiguousarray(np.moveaxis(out.reshape(-1, t_count, 3), 1, 0)).astype(np.float32)
    return Bounce(value, (pv // stride) * shape[1] + pu // stride, np.asarray(phase_us, dtype=np.float64), float(period_us))


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
    mask = np.zeros(h * w, dtype=bool)
    mask[pixels] = True
    mask = mask.reshape(h, w)
    phase = grid_times(period_us, PHASES)
    lit = ~shadows.contains_grid(pixels, t0_us + phase) if len(shadows) else np.ones((PHASES, pixels.size), dtype=bool)
    directions = light.evaluate(t0_us + phase)[0]
    bounce = one_bounce(full_normal.reshape(h, w, 3), full_albedo.reshape(h, w, 3), height, mask, lit, directions, phase, period_us)
    offset = gamma * frame_offsets(problem.frames, bounce, albedo, t0_us, period_us)
    measured = problem.frames.apply_bounce(offset)
    direct_now, direct_ref = direct_irradiance(model, normal, maps, problem.events, geometry.view)
    bounce_now, bounce_ref = event_offsets(problem.events, bounce, albedo, t0_us, period_us)
    share_now = direct_now / np.maximum(direct_now + gamma * bounce_now, 1e-12)
    share_ref = direct_ref / np.maximum(direct_ref + gamma * bounce_ref, 1e-12)
    keep = (share_now >= MIN_DIRECT_SHARE) & (share_ref >= MIN_DIRECT_SHARE)
    shift = np.log(np.maximum(share_now, MIN_DIRECT_SHARE)) - np.log(np.maximum(share_ref, MIN_DIRECT_SHARE))
    problem.events.apply_bounce(shift, keep, gamma * bounce_now, gamma * bounce_ref)
    return {"bounce_frame_share": float(np.mean(offset) / max(float(np.mean(measured)), 1e-12)),
            "bounce_pairs_dropped": float(np.mean(~keep)) if keep.size else 0.0}


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
