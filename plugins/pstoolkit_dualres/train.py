"""The Adam loop of DualResPS over eq. 26 (``train``), in full batches or in the mini-batches of
spatial tiles the paper's network trains on (``mini_batches``).

An epoch with ``batch_pixels`` 0 is one full-batch step on all pixels with ``event_batch`` event
pairs drawn at random (0 = all). Otherwise it is a pass over all pixels in mini-batches of about
``batch_pixels`` frame pixels (one Adam step each): square tiles of ``tile`` frame pixels, shuffled
and offset at random every epoch, each batch taking its pixels' frames, the event pairs of the
super pixels anchored in its tiles, and the TV pairs inside it (as LL22a trains).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor, nn

from pstoolkit import Progress
from pstoolkit.events.rule import LOG_EPS
from pstoolkit_dualres.event_kernel import fused_event_loss
from pstoolkit_dualres.forward_model import frame_prediction, frame_prediction_grid, superpixel_grey
from pstoolkit_dualres.frame_kernel import fused_frame_loss, supports
from pstoolkit_dualres.losses import event_loss, frame_loss, tv_loss
from pstoolkit_dualres.problem import EventTerms, Problem
from pstoolkit_dualres.reflectance import INDIRECT, FitModel

# Final learning rate of a stage as a share of its first: an exponential decay over its epochs.
LR_DECAY = 0.1
PROGRESS_EVERY = 10
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


@dataclass(frozen=True)
class StageConfig:
    """One run of Adam: ``epochs``, learning rates of the surface (``lr``) and of the smooth
    materials (``material_lr``), the loss weights λ_f, λ_e, λ_tv of eq. 26 with the TV term fading
    linearly to zero over the first ``tv_fraction`` of the epochs, ``event_batch`` pairs per step,
    ``batch_pixels``/``tile`` of the mini-batches (0: full batches) and the ``seed`` of the draws."""

    epochs: int
    lr: float
    material_lr: float
    frame_weight: float
    event_weight: float
    event_huber: float
    indirect_sparsity: float
    tv_weight: float
    tv_fraction: float
    event_batch: int
    batch_pixels: int
    tile: int
    seed: int


@dataclass
class Batch:
    """One Adam step's share of the problem. ``pixels`` (N,) the masked-pixel positions the field
    is evaluated at (None: all, in order), the first ``frame_pixels`` of them (None: all) the pixels
    whose frames are fitted; ``frame_rows`` their rows of ``FrameTerms.measured`` in frame-major order
    (None: all); ``samples`` their importance samples (None: all) with ``sample_pixel`` and
    ``sample_group`` (frame·frame_pixels + pixel) in local positions; ``events`` the event pairs
    (indices into all pairs) with ``event_taps`` in local positions; ``tv_pairs`` local neighbour
    pairs."""

    pixels: Tensor | None
    frame_pixels: int | None
    frame_rows: Tensor | None
    samples: Tensor | None
    sample_pixel: Tensor
    sample_group: Tensor
    events: Tensor
    event_taps: Tensor
    tv_pairs: Tensor


def full_batch(problem: Problem, events: Tensor) -> Batch:
    """Every pixel and sample, the event pairs ``events``."""
    return Batch(pixels=None, frame_pixels=None, frame_rows=None, samples=None,
                 sample_pixel=problem.frames.sample_pixel, sample_group=problem.frames.sample_group,
                 events=events, event_taps=problem.events.taps[events], tv_pairs=problem.geometry.tv_pairs)


@dataclass
class Tiling:
    """What ``mini_batches`` needs of a problem, as numpy: each masked pixel's (row, column), each
    usable event pair (``events``, indices into all pairs) with its anchor pixel (its footprint's
    largest tap) and taps, the importance samples' per-pixel ranges and frames, and the TV pairs."""

    row: np.ndarray
    col: np.ndarray
    events: np.ndarray
    event_anchor: np.ndarray
    event_taps: np.ndarray
    sample_start: np.ndarray
    sample_count: np.ndarray
    sample_frame: np.ndarray
    tv_pairs: np.ndarray

    @classmethod
    def of(cls, problem: Problem) -> Tiling:
        geometry, frames = problem.geometry, problem.frames
        p = geometry.pixels.size
        row, col = np.divmod(geometry.pixels, geometry.width)
        events = problem.events.usable.cpu().numpy()
        taps = problem.events.taps.cpu().numpy()[events]
        weight = problem.events.tap_weight_now.cpu().numpy()[events]
        anchor = taps[np.arange(len(taps)), np.argmax(weight, axis=1)] if taps.size else np.zeros(0, np.int64)
        sample_pixel = frames.sample_pixel.cpu().numpy()
        count = np.bincount(sample_pixel, minlength=p)
        return cls(row=row, col=col, events=events, event_anchor=anchor, event_taps=taps,
                   sample_start=np.cumsum(count) - count, sample_count=count,
                   sample_frame=frames.sample_group.cpu().numpy() // max(p, 1),
                   tv_pairs=geometry.tv_pairs.cpu().numpy())


def _ranges(start: np.ndarray, count: np.ndarray) -> np.ndarray:
    """The concatenated index ranges [start_i, start_i + count_i)."""
    total = int(count.sum())
    offsets = np.repeat(start - (np.cumsum(count) - count), count)
    return np.arange(total, dtype=np.int64) + offsets


def mini_batches(problem: Problem, tiling: Tiling, config: StageConfig, generator: torch.Generator) -> list[Batch]:
    """One epoch's mini-batches (see the module docstring): a random tiling offset, tiles in random order
    grouped into batches of about ``config.batch_pixels`` pixels."""
    tile = config.tile
    p = problem.geometry.pixels.size
    shift = torch.randint(0, tile, (2,), generator=generator).numpy()
    rows = (problem.geometry.height + tile) // tile + 1
    cols = (problem.geometry.width + tile) // tile + 1
    tile_of = ((tiling.row + shift[0]) // tile) * cols + (tiling.col + shift[1]) // tile
    rank = torch.randperm(rows * cols, generator=generator).numpy()
    # tiles in random order; a batch closes once it holds batch_pixels pixels
    size = np.bincount(rank[tile_of], minlength=rows * cols)
    batch_of_rank = (np.cumsum(size) - size) // config.batch_pixels
    # a tile larger than batch_pixels skips batch numbers: number the batches densely
    pixel_batch = np.unique(batch_of_rank[rank[tile_of]], return_inverse=True)[1].reshape(-1)
    event_batch = pixel_batch[tiling.event_anchor]
    pair_batch = np.where(pixel_batch[tiling.tv_pairs[:, 0]] == pixel_batch[tiling.tv_pairs[:, 1]],
                          pixel_batch[tiling.tv_pairs[:, 0]], -1)
    by_pixel, by_event, by_pair = (np.argsort(b, kind="stable") for b in (pixel_batch, event_batch, pair_batch))
    n_batches = int(pixel_batch.max()) + 1 if p else 0
    pixel_bounds = np.searchsorted(pixel_batch[by_pixel], np.arange(n_batches + 1))
    event_bounds = np.searchsorted(event_batch[by_event], np.arange(n_batches + 1))
    pair_bounds = np.searchsorted(pair_batch[by_pair], np.arange(n_batches + 1))
    local = np.full(p, -1, dtype=np.int64)
    device = problem.device
    out = []
    for b in range(n_batches):
        own = by_pixel[pixel_bounds[b]:pixel_bounds[b + 1]]
        chosen = by_event[event_bounds[b]:event_bounds[b + 1]]
        taps = tiling.event_taps[chosen]
        # event footprints that reach outside the batch's tiles need those pixels too
        extra = np.setdiff1d(taps, own)
        pixels = np.concatenate([own, extra])
        local[pixels] = np.arange(pixels.size)
        n = own.size
        samples = _ranges(tiling.sample_start[own], tiling.sample_count[own])
        sample_pixel = np.repeat(np.arange(n), tiling.sample_count[own])
        pairs = tiling.tv_pairs[by_pair[pair_bounds[b]:pair_bounds[b + 1]]]

        def tensor(array: np.ndarray) -> Tensor:
            return torch.as_tensor(array, dtype=torch.int64, device=device)

        out.append(Batch(
            pixels=tensor(pixels), frame_pixels=n,
            frame_rows=tensor((np.arange(problem.frames.count)[:, None] * p + own[None, :]).ravel()),
            samples=tensor(samples), sample_pixel=tensor(sample_pixel),
            sample_group=tensor(tiling.sample_frame[samples] * n + sample_pixel),
            events=tensor(tiling.events[chosen]), event_taps=tensor(local[taps]), tv_pairs=tensor(local[pairs]),
        ))
        local[pixels] = -1
    return out


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
           tv_share: float) -> tuple[Tensor, dict[str, float]]:
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
        The step's pixels, frame samples, event pairs and TV pairs.
    tv_share
        Factor on λ_tv (the warm-up's fade from 1 to 0; 0: no TV term).

    Returns
    -------
    total : Tensor
        The scalar loss, differentiable.
    parts : dict
        The parts as floats: "frame", and "event", "tv" and "indirect" (the mean indirect light) when
        they apply.
    """
    normal, pixel_raw, smooth_raw = field(batch.pixels)
    maps = model.maps(pixel_raw, smooth_raw)
    n = batch.frame_pixels
    own_normal, own_maps = (normal, maps) if n is None else (normal[:n], {k: v[:n] for k, v in maps.items()})
    frames, view = problem.frames, problem.geometry.view
    if frames.shared_light is not None:
        visible = frames.shared_visible
        if visible is not None and batch.pixels is not None:
            visible = visible[:, batch.pixels[:n]]
        measured, saturated = frames.measured, frames.saturated
        if batch.frame_rows is not None:
            measured, saturated = measured[batch.frame_rows], saturated[batch.frame_rows]
        lf = grid_frame_loss(model, own_normal, own_maps, frames.shared_light, frames.shared_weight, visible, view,
                             frames.count, measured, saturated, energy=frames.energy)
    else:
        light, weight = frames.sample_light, frames.sample_weight
        if batch.samples is not None:
            light, weight = light[batch.samples], weight[batch.samples]
        predicted = frame_prediction(model, own_normal, own_maps, batch.sample_pixel, batch.sample_group, light, weight,
                                     view, frames.count * own_normal.shape[0], energy=frames.energy)
        measured, saturated = frames.measured, frames.saturated
        if batch.frame_rows is not None:
            measured, saturated = measured[batch.frame_rows], saturated[batch.frame_rows]
        lf = frame_loss(predicted, measured, saturated)
    total = config.frame_weight * lf + field.penalty()
    parts = {"frame": float(lf.detach())}
    if model.indirect:
        # L1: the indirect light stays 0 where the direct light explains the frames
        li = maps[INDIRECT.name].mean()
        total = total + config.indirect_sparsity * li
        parts["indirect"] = float(li.detach())
    e = batch.events
    if e.numel() and config.event_weight > 0:
        le = pair_event_loss(model, normal, maps, batch.event_taps, problem.events, e, view, config.event_huber)
        total = total + config.event_weight * le
        parts["event"] = float(le.detach())
    if tv_share > 0 and config.tv_weight > 0:
        ltv = tv_loss(normal, batch.tv_pairs) + tv_loss(maps[model.diffuse] if model.diffuse else pixel_raw, batch.tv_pairs)
        total = total + config.tv_weight * tv_share * ltv
        parts["tv"] = float(ltv.detach())
    return total, parts


def pair_event_loss(model: FitModel, normal: Tensor, maps: dict[str, Tensor], taps: Tensor, events: EventTerms, pairs: Tensor,
                    view: Tensor, huber: float = 0.0) -> Tensor:
    """The event term of eq. 25 over the event ``pairs`` (indices into ``events``) whose super pixels
    cover the frame pixels ``taps`` (E, F) of ``normal`` (P, 3) and ``maps``: one compiled pass
    (``event_kernel``) for the built-in GGX and Lambertian on the CPU, else ``superpixel_grey`` now and
    at the reference time through ``event_loss``; ``huber`` its δ (0: the square). The scalar loss,
    differentiable."""
    if supports(model, normal):
        return fused_event_loss(model, normal, maps, taps, events, pairs, view, LOG_EPS, huber)
    grey, grey_ref = pair_grey(model, normal, maps, taps, events, pairs, view)
    return event_loss(grey, grey_ref, events.target[pairs], events.weight[pairs], LOG_EPS, huber)


def pair_grey(model: FitModel, normal: Tensor, maps: dict[str, Tensor], taps: Tensor, events: EventTerms, pairs: Tensor,
              view: Tensor) -> tuple[Tensor, Tensor]:
    """(E,) each pair's ``superpixel_grey`` now and at its reference time, through torch."""
    area = events.tap_area[pairs] if model.indirect else None
    grey = superpixel_grey(model, normal, maps, taps, events.tap_weight_now[pairs], events.light_now[pairs],
                           events.grey_now[pairs], view, area)
    grey_ref = superpixel_grey(model, normal, maps, taps, events.tap_weight_ref[pairs], events.light_ref[pairs],
                               events.grey_ref[pairs], view, area)
    return grey, grey_ref


def _event_sample(problem: Problem, config: StageConfig, generator: torch.Generator) -> Tensor:
    """``event_batch`` of the usable pairs at random (all of them at 0), in the pairs' order: grouped by
    super pixel, so that a step reads the pixels' maps in memory order."""
    usable = problem.events.usable
    if 0 < config.event_batch < usable.numel():
        chosen = torch.randperm(usable.numel(), generator=generator)[: config.event_batch]
        return usable[torch.sort(chosen).values.to(usable.device)]
    return usable


def train(problem: Problem, field: nn.Module, model: FitModel, config: StageConfig, progress: Progress,
          warm_start: bool = False) -> list[dict[str, float]]:
    """Adam over ``config.epochs`` epochs on eq. 26, the learning rates decaying exponentially to
    ``LR_DECAY`` of their first.

    Parameters
    ----------
    problem, field, model
        As for ``losses``; the field's parameters and the model's own (if any) are fitted.
    config
        The stage: epochs, learning rates, loss weights, batches and seed.
    progress
        ``progress(fraction, message)``, called at every PROGRESS_EVERY-th epoch and the last.
    warm_start
        Skips the TV warm-up (a later stage).

    Returns
    -------
    list of dict
        For every PROGRESS_EVERY-th epoch and the last: "epoch", "steps" and the loss and its parts,
        means over the epoch's batches.
    """
    generator = torch.Generator(device="cpu").manual_seed(config.seed)
    groups = [{"params": field.surface_parameters(), "lr": config.lr}]
    materials = [*field.material_parameters(), *model.parameters()]
    if materials:
        groups.append({"params": materials, "lr": config.material_lr if field.material_parameters() else config.lr})
    optimizer = torch.optim.Adam(groups)
    scheduler = torch.optim.lr_scheduler.ExponentialLR(optimizer, LR_DECAY ** (1.0 / max(config.epochs, 1)))
    tiling = Tiling.of(problem) if config.batch_pixels > 0 else None
    history: list[dict[str, float]] = []
    warmup = max(config.tv_fraction * config.epochs, 1e-9)
    for epoch in range(config.epochs):
        if tiling is None:
            batches = [full_batch(problem, _event_sample(problem, config, generator))]
        else:
            batches = mini_batches(problem, tiling, config, generator)
        totals: dict[str, float] = {}
        tv_share = 0.0 if warm_start else max(0.0, 1.0 - epoch / warmup)
        for batch in batches:
            # before the losses: the chunked frame term already adds to the model's own gradients
            optimizer.zero_grad(set_to_none=True)
            loss, parts = losses(problem, field, model, config, batch, tv_share)
            loss.backward()
            optimizer.step()
            for name, value in {"loss": float(loss.detach()), **parts}.items():
                totals[name] = totals.get(name, 0.0) + value / len(batches)
        scheduler.step()
        if epoch % PROGRESS_EVERY == 0 or epoch == config.epochs - 1:
            history.append({"epoch": float(epoch), "steps": float(len(batches)), **totals})
            progress((epoch + 1) / config.epochs, f"epoch {epoch + 1}/{config.epochs} loss {totals['loss']:.4g}")
    return history
