"""The Adam loop of DualResPS over eq. 26 (``train``), in full batches or in the mini-batches of
spatial tiles the paper's network trains on (``mini_batches``).

An epoch with ``batch_pixels`` 0 is one full-batch step on all pixels with ``event_batch`` event
pairs drawn at random (0 = all). Otherwise it is a pass over all pixels in mini-batches of about
``batch_pixels`` frame pixels (one Adam step each): square tiles of ``tile`` frame pixels, shuffled
and offset at random every epoch, each batch taking its pixels' frames, the event pairs of the
super pixels anchored in its tiles, and the TV pairs inside it (as LL22a trains).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor, nn

from pstoolkit import Progress
from pstoolkit_dualres.losses import losses
from pstoolkit_dualres.problem import Problem
from pstoolkit_dualres.reflectance import FitModel

# Final learning rate of a stage as a share of its first: an exponential decay over its epochs.
LR_DECAY = 0.1
PROGRESS_EVERY = 10


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
    arrays: list[tuple[int, dict[str, np.ndarray]]] = []
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
        arrays.append((n, {
            "pixels": pixels, "frame_rows": (np.arange(problem.frames.count)[:, None] * p + own[None, :]).ravel(),
            "samples": samples, "sample_pixel": sample_pixel, "sample_group": tiling.sample_frame[samples] * n + sample_pixel,
            "events": tiling.events[chosen], "event_taps": local[taps], "tv_pairs": local[pairs],
        }))
        local[pixels] = -1
    return _moved(arrays, problem.device)


def _moved(arrays: list[tuple[int, dict[str, np.ndarray]]], device: torch.device) -> list[Batch]:
    """The batches of these (``frame_pixels``, index arrays by field) on ``device``, the arrays moved in
    one copy: on a GPU a copy for each batch and array would wait for the device each time."""
    if not arrays:
        return []
    moved = torch.as_tensor(np.concatenate([a.ravel() for _, batch in arrays for a in batch.values()], dtype=np.int64), device=device)
    out, start = [], 0
    for n, batch in arrays:
        views = {}
        for name, a in batch.items():
            views[name] = moved[start:start + a.size].view(a.shape)
            start += a.size
        out.append(Batch(frame_pixels=n, **views))
    return out


def _event_sample(problem: Problem, config: StageConfig, generator: torch.Generator) -> Tensor:
    """``event_batch`` of the usable pairs at random (all of them at 0), in the pairs' order: grouped by
    super pixel, so that a step reads the pixels' maps in memory order."""
    usable = problem.events.usable
    if 0 < config.event_batch < usable.numel():
        chosen = torch.randperm(usable.numel(), generator=generator)[: config.event_batch]
        return usable[torch.sort(chosen).values.to(usable.device)]
    return usable


def train(problem: Problem, field: nn.Module, model: FitModel, config: StageConfig, progress: Progress,
          warm_start: bool = False, before_epoch: Callable[[int], None] | None = None) -> list[dict[str, float]]:
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
    before_epoch
        Called with each epoch's index (within the stage) before its batches: what the solver
        re-estimates from the fit as it goes (``thresholds``).

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
        if before_epoch is not None:
            before_epoch(epoch)
        if tiling is None:
            batches = [full_batch(problem, _event_sample(problem, config, generator))]
        else:
            batches = mini_batches(problem, tiling, config, generator)
        totals: dict[str, Tensor] = {}
        tv_share = 0.0 if warm_start else max(0.0, 1.0 - epoch / warmup)
        for batch in batches:
            # before the losses: the chunked frame term already adds to the model's own gradients
            optimizer.zero_grad(set_to_none=True)
            loss, parts = losses(problem, field, model, config, batch, tv_share)
            loss.backward()
            optimizer.step()
            # kept as tensors: reading a value each step would wait for the device each step
            for name, value in {"loss": loss.detach(), **parts}.items():
                share = value.to(torch.float64) / len(batches)
                totals[name] = totals[name] + share if name in totals else share
        scheduler.step()
        if epoch % PROGRESS_EVERY == 0 or epoch == config.epochs - 1:
            means = {name: float(value) for name, value in totals.items()}
            history.append({"epoch": float(epoch), "steps": float(len(batches)), **means})
            progress((epoch + 1) / config.epochs, f"epoch {epoch + 1}/{config.epochs} loss {means['loss']:.4g}")
    return history
