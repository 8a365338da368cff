"""The training losses of DualResPS (eq. 24–26).

- Frames (eq. 24): mean L1 between rendered and measured frame values. A value the sensor clipped
  (``saturated``) only says the truth was at least 1: it is penalised only while the rendering stays
  below 1, so highlights that clip do not pull the fit down.
- Events (eq. 25): weighted squared residual of the log ratio of the rendered grey irradiance at an
  event and at its reference time against the fired contrast: ln((Ĩ_k + ε)/(Ĩ_ref + ε)) − ln α − p·C;
  with a Huber δ (``robust_square``) a residual beyond δ counts linearly, so the pairs the model cannot
  explain — noise events, a threshold off its nominal value, light reflected from other parts of the
  object — pull the fit with a bounded force instead of one that grows with their residual.
- Total variation (eq. 26, the warm-up term of LL22a): mean L1 difference of neighbouring pixels.

``losses`` sums them as eq. 26 weighs them on one batch of ``train``: the frame term through
``grid_frame_loss`` (one compiled pass for the built-in BRDFs, ``frame_kernel``, else torch in chunks
of pixels) or, without a shared time grid, through ``frame_prediction``; the event term through
``pair_event_loss`` (``event_kernel``, else ``pair_grey`` and ``event_loss``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import torch
from torch import Tensor, nn

from pstoolkit.events.rule import LOG_EPS
from pstoolkit_dualres.event_kernel import fused_event_loss
from pstoolkit_dualres.forward_model import frame_prediction, frame_prediction_grid, shade_rows, superpixel_grey, tap_rows
from pstoolkit_dualres.frame_kernel import fused_frame_loss, supports
from pstoolkit_dualres.gather import gather_sum
from pstoolkit_dualres.problem import EventTerms, Problem
from pstoolkit_dualres.reflectance import INDIRECT, FitModel

if TYPE_CHECKING:
    from pstoolkit_dualres.batches import Batch, Valid
    from pstoolkit_dualres.train import StageConfig

# Pixels per chunk of the frame term on the shared time grid (``grid_frame_loss``): the rendering's
# intermediates, (chunk, K·S, 3) float32 each (4.5 MiB at 16384 pixels and K·S = 24), stay below
# glibc's largest mmap threshold (32 MiB), so the allocator reuses them from chunk to chunk instead
# of mapping and faulting in fresh pages for every tensor of every step.
FRAME_CHUNK = 16384
# On a GPU, chunks as large as half its free memory holds for the chunk's graph (bytes per pixel and
# sample: the whole term's graph was some 10 kB per pixel at K·S = 24), up to CUDA_FRAME_CHUNK pixels:
# fewer, larger kernels (a 1024² solve's training 3× faster on an H200 than in chunks of FRAME_CHUNK,
# docs/dualres-tuning.md).
GRAPH_BYTES_PER_SAMPLE = 512
CUDA_FRAME_CHUNK = 1 << 20


def share_mean(values: Tensor, valid: Valid | None = None) -> Tensor:
    """The mean of ``values`` (N, ...), or where ``valid`` is given the mean over the rows it marks
    (a padded batch's, ``batches.Padding``)."""
    if valid is None:
        return values.mean()
    marked = values * valid.mask.view((-1,) + (1,) * (values.dim() - 1))
    return marked.sum() / (valid.count.clamp(min=1) * (values[0].numel() if values.shape[0] else 1))


def frame_loss(predicted: Tensor, measured: Tensor, saturated: Tensor, valid: Valid | None = None) -> Tensor:
    """Mean |Ã − A| over (values, 3) (over the rows ``valid`` marks, where given); ``saturated``
    (values,) bool marks clipped measurements."""
    residual = torch.where(saturated[:, None], torch.relu(1.0 - predicted), (predicted - measured).abs())
    return share_mean(residual, valid)


def robust_square(residual: Tensor, huber: float) -> Tensor:
    """r² within ``huber`` δ (all of it for δ ≤ 0), 2δ|r| − δ² beyond: Huber's loss times two, so that
    within δ it is the plain square of eq. 25."""
    if huber <= 0:
        return residual * residual
    clipped = residual.clamp(-huber, huber)
    return clipped * (2.0 * residual - clipped)


def event_loss(grey_t: Tensor, grey_ref: Tensor, target: Tensor, weight: Tensor, eps: float, huber: float = 0.0,
               valid: Valid | None = None) -> Tensor:
    """Σ w·ρ_δ(ln((Ĩ_k + ε)/(Ĩ_ref + ε)) − target) / N_e with ``target`` = ln α + p·C per event pair and
    ρ_δ = ``robust_square`` (δ = ``huber``, log units); over the pairs ``valid`` marks, where given."""
    terms = weight * robust_square(log_residual(grey_t, grey_ref, target, eps), huber)
    if valid is None:
        return torch.sum(terms) / max(int(target.numel()), 1)
    return torch.sum(terms * valid.mask) / valid.count.clamp(min=1)


def log_residual(grey_t: Tensor, grey_ref: Tensor, target: Tensor, eps: float) -> Tensor:
    """The event residual of eq. 25 per pair: ln((Ĩ_k + ε)/(Ĩ_ref + ε)) − target."""
    return torch.log(grey_t + eps) - torch.log(grey_ref + eps) - target


def tv_loss(values: Tensor, pairs: Tensor, valid: Valid | None = None) -> Tensor:
    """Mean |v_a − v_b| over neighbour pairs (Q, 2) of rows of ``values`` (P, C) (over those ``valid``
    marks, where given)."""
    if pairs.numel() == 0:
        return values.sum() * 0.0
    # the signs made on the device: a tensor of host data is a copy that a CUDA graph cannot capture
    one = values.new_ones((1, 1))
    difference = torch.cat([one, -one], dim=1).expand(pairs.shape[0], 2)
    return share_mean(gather_sum(values, pairs, difference).abs(), valid)


def frame_chunk(normal: Tensor, samples: int) -> int:
    """Pixels per chunk of ``grid_frame_loss`` on ``normal``'s device for ``samples`` (K·S) light
    samples: FRAME_CHUNK on the CPU; on a GPU what half its free memory holds at
    GRAPH_BYTES_PER_SAMPLE per pixel and sample, between FRAME_CHUNK and CUDA_FRAME_CHUNK."""
    if normal.device.type != "cuda":
        return FRAME_CHUNK
    free_bytes, _ = torch.cuda.mem_get_info(normal.device)
    fits = free_bytes // 2 // (max(samples, 1) * GRAPH_BYTES_PER_SAMPLE)
    return int(min(CUDA_FRAME_CHUNK, max(FRAME_CHUNK, fits)))



def grid_frame_loss(model: FitModel, normal: Tensor, maps: dict[str, Tensor], light: Tensor, weight: Tensor,
                    visible: Tensor | None, view: Tensor, frames: int, measured: Tensor, saturated: Tensor,
                    chunk: int | None = None, energy: Tensor | None = None) -> Tensor:
    """``frame_loss`` of ``frame_prediction_grid`` over all P pixels: for the built-in GGX and
    Lambertian on the CPU in one compiled pass with its own derivatives (``frame_kernel``), for any
    other BRDF through torch with its graph held one chunk of ``chunk`` pixels at a time.

    With gradients enabled, each chunk's rendering is differentiated at once into the gradient of
    the loss with respect to ``normal`` and ``maps`` (and into the ``.grad`` of the model's own
    parameters, if any: zero them before calling), then freed; the result is the loss value plus a
    term that is zero in value and whose gradient with respect to ``normal`` and ``maps`` is the one
    gathered, so the caller's backward carries it on. The (P, K·S, 3) graph of the whole frame term —
    some 10 kB per pixel, whose pages were faulted in afresh every step — never exists: a step's
    time and memory grow linearly with P (numbers in benchmarks/dualres_scale.py).

    Parameters
    ----------
    model, light, weight, view, frames
        As for ``frame_prediction_grid``: the BRDF, (K·S, 3) light directions and weights, (3,) view
        direction, K frames.
    normal
        (P, 3) unit normals.
    maps
        The BRDF's maps, (P, channels) each.
    visible
        (K·S, P) lit share of each sample, or None.
    measured, saturated
        (K·P, 3) frame values and (K·P,) clipped flags, rows frame·P + pixel.
    chunk
        Pixels per chunk (default ``frame_chunk``).
    energy
        (K, 3) each frame's light energy (``FrameTerms.energy``), for a model with indirect light.

    Returns
    -------
    Tensor
        The scalar mean |Ã − A| of ``frame_loss`` (equal up to float rounding of the chunked sum).
    """
    if supports(model, normal):
        return fused_frame_loss(model, normal, maps, light, weight, visible, view, frames, measured, saturated, energy)
    p = normal.shape[0]
    chunk = frame_chunk(normal, light.shape[0]) if chunk is None else chunk
    if p <= chunk:
        predicted = frame_prediction_grid(model, normal, maps, light, weight, visible, view, frames, energy)
        return frame_loss(predicted, measured, saturated)
    names = list(maps)
    inputs = [normal, *(maps[name] for name in names)]
    differentiate = torch.is_grad_enabled() and any(x.requires_grad for x in inputs)
    measured_k, saturated_k = measured.reshape(frames, p, -1), saturated.reshape(frames, p)
    value = normal.new_zeros(())
    grads: list[list[Tensor]] = [[] for _ in inputs]
    for start in range(0, p, chunk):
        part = slice(start, start + chunk)
        # leaves of the chunk's own rows: a slice of a whole-P leaf would backward into a (P, C) buffer per chunk
        leaves = [x[part].detach().requires_grad_(differentiate and x.requires_grad) for x in inputs]
        predicted = frame_prediction_grid(model, leaves[0], dict(zip(names, leaves[1:])), light, weight,
                                          None if visible is None else visible[:, part], view, frames, energy)
        rows = measured_k[:, part].reshape(predicted.shape)
        # frame_loss is a mean: each chunk weighs by its share of the values
        loss = frame_loss(predicted, rows, saturated_k[:, part].reshape(-1)) * (predicted.shape[0] / (frames * p))
        if differentiate:
            loss.backward()
            for store, leaf in zip(grads, leaves):
                store.append(leaf.grad if leaf.grad is not None else torch.zeros_like(leaf))
        value = value + loss.detach()
    if not differentiate:
        return value
    dot = sum(torch.sum(x * torch.cat(g)) for x, g in zip(inputs, grads) if x.requires_grad)
    # zero in value, the gathered gradient in backward
    return value + (dot - dot.detach())



def losses(problem: Problem, field: nn.Module, model: FitModel, config: StageConfig, batch: Batch,
           tv_share: float | Tensor) -> tuple[Tensor, dict[str, Tensor]]:
    """The total loss of eq. 26 (with the field's own smoothness penalty) and its parts on ``batch``.

    Parameters
    ----------
    problem
        The fit's tensors, with the current cast-shadow mask applied.
    field
        The surface and material field (``fields``): ``field(pixels)`` gives the normals and raw
        channels at those masked pixels, ``field.penalty()`` its own smoothness penalty.
    model
        The fitted BRDF, which turns the raw channels into maps.
    config
        The stage's loss weights λ_f, λ_e, λ_tv.
    batch
        The step's pixels, frame samples, event pairs and TV pairs; a padded batch's means are taken
        over the rows its ``padding`` marks.
    tv_share
        Factor on λ_tv (the warm-up's fade from 1 to 0; 0: no TV term); a tensor (a CUDA graph's
        input) always adds the term.

    Returns
    -------
    total : Tensor
        The scalar loss, differentiable.
    parts : dict
        The parts as detached scalar tensors (on the problem's device: reading one waits for the
        device): "frame", and "event", "tv" and "indirect" (the mean indirect light) when they apply.
    """
    normal, pixel_raw, smooth_raw = field(batch.pixels)
    maps = model.maps(pixel_raw, smooth_raw)
    n, pad = batch.frame_pixels, batch.padding
    rendered: tuple[PairRows, Tensor] | None = None
    own_normal, own_maps = (normal, maps) if n is None else (normal[:n], {k: v[:n] for k, v in maps.items()})
    frames, view = problem.frames, problem.geometry.view
    if frames.shared_light is not None:
        visible = frames.shared_visible
        if visible is not None and batch.pixels is not None:
            visible = visible[:, batch.pixels[:n]]
        measured, saturated = frames.measured, frames.saturated
        if batch.frame_rows is not None:
            measured, saturated = measured[batch.frame_rows], saturated[batch.frame_rows]
        if pad is None:
            lf = grid_frame_loss(model, own_normal, own_maps, frames.shared_light, frames.shared_weight, visible, view,
                                 frames.count, measured, saturated, chunk=batch.frame_chunk, energy=frames.energy)
        else:
            predicted = frame_prediction_grid(model, own_normal, own_maps, frames.shared_light, frames.shared_weight, visible,
                                              view, frames.count, frames.energy)
            lf = frame_loss(predicted, measured, saturated, pad.frame)
    else:
        light, weight = frames.sample_light, frames.sample_weight
        if batch.samples is not None:
            light, weight = light[batch.samples], weight[batch.samples]
        if pad is not None:
            weight = weight * pad.sample.mask[:, None]
        sample_shaded = None
        if batch.events.numel() and config.event_weight > 0 and (pad is not None or not supports(model, normal)):
            # the samples and the pairs' taps in one rendering: half the kernels of two (on a GPU, a step's time)
            rows = pair_rows(batch.event_taps, problem.events, batch.events, model.indirect)
            pixel, tap_light = tap_rows(rows.taps, rows.light)
            shaded = shade_rows(model, normal, maps, torch.cat([batch.sample_pixel, pixel]), torch.cat([light, tap_light]), view)
            sample_shaded, rendered = shaded[: light.shape[0]], (rows, shaded[light.shape[0]:])
        predicted = frame_prediction(model, own_normal, own_maps, batch.sample_pixel, batch.sample_group, light, weight,
                                     view, frames.count * own_normal.shape[0], energy=frames.energy, shaded=sample_shaded)
        measured, saturated = frames.measured, frames.saturated
        if batch.frame_rows is not None:
            measured, saturated = measured[batch.frame_rows], saturated[batch.frame_rows]
        lf = frame_loss(predicted, measured, saturated, None if pad is None else pad.frame)
    total = config.frame_weight * lf + field.penalty()
    parts = {"frame": lf.detach()}
    if model.indirect:
        # L1: the indirect light stays 0 where the direct light explains the frames
        li = share_mean(maps[INDIRECT.name], None if pad is None else pad.pixel)
        total = total + config.indirect_sparsity * li
        parts["indirect"] = li.detach()
    e = batch.events
    if e.numel() and config.event_weight > 0:
        le = pair_event_loss(model, normal, maps, batch.event_taps, problem.events, e, view, config.event_huber,
                             None if pad is None else pad.event, rendered)
        total = total + config.event_weight * le
        parts["event"] = le.detach()
    if config.tv_weight > 0 and (isinstance(tv_share, Tensor) or tv_share > 0):
        tv = None if pad is None else pad.tv
        ltv = tv_loss(normal, batch.tv_pairs, tv) + tv_loss(maps[model.diffuse] if model.diffuse else pixel_raw, batch.tv_pairs, tv)
        total = total + config.tv_weight * tv_share * ltv
        parts["tv"] = ltv.detach()
    return total, parts



def pair_event_loss(model: FitModel, normal: Tensor, maps: dict[str, Tensor], taps: Tensor, events: EventTerms, pairs: Tensor,
                    view: Tensor, huber: float = 0.0, valid: Valid | None = None,
                    rendered: tuple[PairRows, Tensor] | None = None) -> Tensor:
    """The event term of eq. 25 over the event ``pairs`` (indices into ``events``) whose super pixels
    cover the frame pixels ``taps`` (E, F) of ``normal`` (P, 3) and ``maps``: one compiled pass
    (``event_kernel``) for the built-in GGX and Lambertian on the CPU, else ``superpixel_grey`` now and
    at the reference time through ``event_loss``; ``huber`` its δ (0: the square); over the pairs
    ``valid`` marks, where given, and with the pairs' rows and their taps' shading ``rendered`` by the
    caller (``pair_grey``; both through torch). The scalar loss, differentiable."""
    if valid is None and rendered is None and supports(model, normal):
        return fused_event_loss(model, normal, maps, taps, events, pairs, view, LOG_EPS, huber)
    grey, grey_ref = pair_grey(model, normal, maps, taps, events, pairs, view, rendered)
    return event_loss(grey, grey_ref, events.target[pairs], events.weight[pairs], LOG_EPS, huber, valid)


class PairRows(NamedTuple):
    """Event pairs now and at their reference times, one after the other, as ``superpixel_grey``
    takes them: (2E, F) ``taps`` and their ``weight``, (2E, 3) ``light`` and ``grey`` intensities, and
    (2E, F) the taps' ``area`` (None: not asked for)."""

    taps: Tensor
    weight: Tensor
    light: Tensor
    grey: Tensor
    area: Tensor | None


def pair_rows(taps: Tensor, events: EventTerms, pairs: Tensor, area: bool) -> PairRows:
    """The ``pairs`` (E,) (indices into ``events``) whose super pixels cover ``taps`` (E, F) as
    ``PairRows``, with their taps' areas where ``area``."""
    return PairRows(torch.cat([taps, taps]), torch.cat([events.tap_weight_now[pairs], events.tap_weight_ref[pairs]]),
                    torch.cat([events.light_now[pairs], events.light_ref[pairs]]),
                    torch.cat([events.grey_now[pairs], events.grey_ref[pairs]]),
                    torch.cat([events.tap_area[pairs]] * 2) if area else None)


def pair_grey(model: FitModel, normal: Tensor, maps: dict[str, Tensor], taps: Tensor, events: EventTerms, pairs: Tensor,
              view: Tensor, rendered: tuple[PairRows, Tensor] | None = None) -> tuple[Tensor, Tensor]:
    """(E,) each pair's ``superpixel_grey`` now and at its reference time, through torch, both in one
    rendering (half the kernels of two: on a GPU, a step's time is their count); ``rendered`` the
    ``pair_rows`` (with the areas where the model has indirect light) and the (2E·F, 3) rendering of
    their taps, where the caller made them."""
    count = pairs.numel()
    rows, shaded = rendered if rendered is not None else (pair_rows(taps, events, pairs, model.indirect), None)
    both = superpixel_grey(model, normal, maps, rows.taps, rows.weight, rows.light, rows.grey, view, rows.area, shaded)
    return both[:count], both[count:]
