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
from pstoolkit._shared import devices
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
    """What ``mini_batches`` needs of a problem: as numpy, each masked pixel's (row, column), each
    usable event pair (``events``, indices into all pairs) with its anchor pixel (its footprint's
    largest tap) and taps, and the TV pairs; on the problem's device, each pixel's first importance
    sample and count of them (the samples are stored by pixel) and each sample's frame."""

    row: np.ndarray
    col: np.ndarray
    events: np.ndarray
    event_anchor: np.ndarray
    event_taps: np.ndarray
    tv_pairs: np.ndarray
    sample_start: Tensor
    sample_count: Tensor
    sample_frame: Tensor

    @classmethod
    def of(cls, problem: Problem) -> Tiling:
        geometry, frames = problem.geometry, problem.frames
        p = geometry.pixels.size
        row, col = np.divmod(geometry.pixels, geometry.width)
        events = problem.events.usable.cpu().numpy()
        taps = problem.events.taps.cpu().numpy()[events]
        weight = problem.events.tap_weight_now.cpu().numpy()[events]
        anchor = taps[np.arange(len(taps)), np.argmax(weight, axis=1)] if taps.size else np.zeros(0, np.int64)
        count = torch.bincount(frames.sample_pixel, minlength=p)
        return cls(row=row, col=col, events=events, event_anchor=anchor, event_taps=taps,
                   tv_pairs=geometry.tv_pairs.cpu().numpy(), sample_start=torch.cumsum(count, 0) - count,
                   sample_count=count, sample_frame=frames.sample_group // max(p, 1))


def _starts(count: np.ndarray) -> np.ndarray:
    """Where each of consecutive blocks of ``count`` entries starts."""
    return np.cumsum(count) - count


def mini_batches(problem: Problem, tiling: Tiling, config: StageConfig, generator: torch.Generator) -> list[Batch]:
    """One epoch's mini-batches (see the module docstring): a random tiling offset, tiles in random order
    grouped into batches of about ``config.batch_pixels`` pixels.

    A batch's pixels are its own (in the masked pixels' order), then the pixels its event pairs'
    footprints reach outside its tiles (ascending); its frame rows and samples follow its own pixels'
    order. Every batch is built at once: the arrays of pixels, pairs and TV pairs on the host, moved to
    the problem's device in one copy, the samples' (some 80 per pixel) there."""
    tile = config.tile
    p = problem.geometry.pixels.size
    if p == 0:
        return []
    shift = torch.randint(0, tile, (2,), generator=generator).numpy()
    rows = (problem.geometry.height + tile) // tile + 1
    cols = (problem.geometry.width + tile) // tile + 1
    tile_of = ((tiling.row + shift[0]) // tile) * cols + (tiling.col + shift[1]) // tile
    rank = torch.randperm(rows * cols, generator=generator).numpy()
    # tiles in random order; a batch closes once it holds batch_pixels pixels
    size = np.bincount(rank[tile_of], minlength=rows * cols)
    batch_of_rank = _starts(size) // config.batch_pixels
    # a tile larger than batch_pixels skips batch numbers: number the batches densely
    pixel_batch = np.unique(batch_of_rank[rank[tile_of]], return_inverse=True)[1].reshape(-1)
    event_batch = pixel_batch[tiling.event_anchor]
    pair_batch = np.where(pixel_batch[tiling.tv_pairs[:, 0]] == pixel_batch[tiling.tv_pairs[:, 1]],
                          pixel_batch[tiling.tv_pairs[:, 0]], -1)
    by_pixel, by_event, by_pair = (np.argsort(b, kind="stable") for b in (pixel_batch, event_batch, pair_batch))
    n_batches = int(pixel_batch.max()) + 1
    own_count = np.bincount(pixel_batch, minlength=n_batches)
    event_count = np.bincount(event_batch, minlength=n_batches)
    pair_count = np.bincount(pair_batch[pair_batch >= 0], minlength=n_batches)
    # each pixel's place among its batch's own pixels, and its batch's count of them
    own_rank = np.empty(p, dtype=np.int64)
    own_rank[by_pixel] = np.arange(p) - np.repeat(_starts(own_count), own_count)
    own_of = own_count[pixel_batch[by_pixel]]
    # the footprints' pixels outside their pair's batch, unique and ascending within each batch
    taps = tiling.event_taps[by_event]
    tap_batch = np.repeat(event_batch[by_event], taps.shape[1]).reshape(taps.shape)
    outside = pixel_batch[taps] != tap_batch
    extra_key = np.unique(tap_batch[outside] * p + taps[outside])
    extra_batch, extra_pixel = np.divmod(extra_key, p)
    extra_count = np.bincount(extra_batch, minlength=n_batches)
    extra_place = own_count[extra_batch] + np.arange(extra_key.size) - np.repeat(_starts(extra_count), extra_count)
    local_taps = own_rank[taps]
    local_taps[outside] = extra_place[np.searchsorted(extra_key, tap_batch[outside] * p + taps[outside])]
    pixel_count = own_count + extra_count
    pixels = np.empty(int(pixel_count.sum()), dtype=np.int64)
    pixel_start = _starts(pixel_count)
    pixels[pixel_start[pixel_batch[by_pixel]] + own_rank[by_pixel]] = by_pixel
    pixels[pixel_start[extra_batch] + extra_place] = extra_pixel
    # frame rows frame-major within each batch: frame·P + pixel for each frame, then the next
    frames = problem.frames.count
    frame_rows = np.empty(frames * p, dtype=np.int64)
    row_start = frames * _starts(own_count)[pixel_batch[by_pixel]] + own_rank[by_pixel]
    for k in range(frames):
        frame_rows[row_start + k * own_of] = k * p + by_pixel
    pairs = tiling.tv_pairs[by_pair[by_pair.size - int(pair_count.sum()):]]
    sample_count = tiling.sample_count.cpu().numpy()
    moved = _moved({"pixels": pixels, "frame_rows": frame_rows, "events": tiling.events[by_event], "event_taps": local_taps,
                    "tv_pairs": own_rank[pairs]}, problem.device)
    rows_of = {"pixels": pixel_count, "frame_rows": frames * own_count, "events": event_count, "event_taps": event_count,
               "tv_pairs": pair_count}
    parts = {name: torch.split(moved[name], rows_of[name].tolist()) for name in rows_of}
    sample_rows = np.bincount(pixel_batch, weights=sample_count, minlength=n_batches).astype(np.int64).tolist()
    for name, value in _samples(tiling, by_pixel, own_rank[by_pixel], own_of).items():
        parts[name] = torch.split(value, sample_rows)
    return [Batch(frame_pixels=int(n), **{name: split[b] for name, split in parts.items()}) for b, n in enumerate(own_count)]


def _moved(arrays: dict[str, np.ndarray], device: torch.device) -> dict[str, Tensor]:
    """These int64 arrays on ``device``, moved in one copy: on a GPU a copy for each batch and array would
    wait for the device each time."""
    moved = torch.as_tensor(np.concatenate([a.ravel() for a in arrays.values()], dtype=np.int64), device=device)
    out, start = {}, 0
    for name, a in arrays.items():
        out[name] = moved[start:start + a.size].view(a.shape)
        start += a.size
    return out


def _samples(tiling: Tiling, order: np.ndarray, rank: np.ndarray, own: np.ndarray) -> dict[str, Tensor]:
    """The importance samples of the masked pixels ``order`` (P,), each pixel's in their stored order:
    "samples" their indices into all samples, "sample_pixel" the ``rank`` of their pixel among its
    batch's own pixels, "sample_group" frame·``own`` + rank (``own`` each pixel's batch's count of own
    pixels). In numpy on the host (faster there than torch), in torch on a device (some 80 samples a
    pixel: moving their indices each epoch would take longer than making them there)."""
    start, count, frame = tiling.sample_start, tiling.sample_count, tiling.sample_frame
    total = int(frame.numel())
    if devices.on_host(count.device):
        count_np = count.numpy()[order]
        offset = np.repeat(start.numpy()[order] - (np.cumsum(count_np) - count_np), count_np)
        samples = np.arange(total, dtype=np.int64) + offset
        sample_pixel = np.repeat(rank, count_np)
        group = frame.numpy()[samples] * np.repeat(own, count_np) + sample_pixel
        return {"samples": torch.from_numpy(samples), "sample_pixel": torch.from_numpy(sample_pixel),
                "sample_group": torch.from_numpy(group)}
    there = _moved({"order": order, "rank": rank, "own": own}, count.device)
    count = count[there["order"]]
    offset = torch.repeat_interleave(start[there["order"]] - (torch.cumsum(count, 0) - count), count, output_size=total)
    samples = torch.arange(total, device=count.device) + offset
    sample_pixel = torch.repeat_interleave(there["rank"], count, output_size=total)
    group = frame[samples] * torch.repeat_interleave(there["own"], count, output_size=total) + sample_pixel
    return {"samples": samples, "sample_pixel": sample_pixel, "sample_group": group}


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
