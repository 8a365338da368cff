"""Neural inverse rendering of DualResPS (main §3.3): the preprocessed captures turned into tensors
(``build_problem``) and the Adam loop over eq. 26 (``train``).

Units: frame values in units of saturation; albedo and F0 in units of ``albedo_scale`` (a bright
albedo of the capture, in frame units per unit light per second), which the frame sample weights
carry; the event irradiance is e·f_r·[n·l]₊ in those units, so a bright lit pixel is ≈ 1 as the
event model's ε assumes (``pstoolkit.eventmodel``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from pstoolkit.equivalent import sample_times
from pstoolkit.eventmodel import LOG_EPS
from pstoolkit.lights import US_PER_S
from pstoolkit.render import GREY_WEIGHTS, area_weights
from pstoolkit.solver import Progress
from pstoolkit_dualres.grid import bilinear_taps, frame_to_event
from pstoolkit_dualres.losses import event_loss, frame_loss, tv_loss
from pstoolkit_dualres.model import GridField, NeuralField
from pstoolkit_dualres.render import (
    Reflectance,
    frame_prediction,
    frame_prediction_grid,
    superpixel_grey,
)

# Percentile of the initial grey albedo over the mask taken as the albedo scale: a bright albedo
# that ignores the few outliers of the closed form near the terminator.
SCALE_PERCENTILE = 95.0
# Final learning rate as a share of the first: an exponential decay over the epochs.
LR_DECAY = 0.1
PROGRESS_EVERY = 10


@dataclass
class TrainConfig:
    """Hyper-parameters of one fit: ``epochs`` passes over the data, learning rates of the
    normal/albedo parameters (``lr``) and of the materials (``material_lr``), decaying exponentially
    to ``LR_DECAY`` of their start over the epochs, the loss weights λ_f, λ_e, λ_tv of eq. 26 with
    the TV term fading linearly to zero over the first ``tv_fraction`` of the epochs, and
    ``frame_samples`` per frame on a time grid shared by all pixels (0 = the importance samples of
    preprocessing).

    ``batch_pixels`` 0: an epoch is one full-batch Adam step on all pixels, with ``event_batch``
    event pairs drawn at random (0 = all). Otherwise an epoch is a pass over all pixels in
    mini-batches of about ``batch_pixels`` frame pixels (one Adam step each): square tiles of
    ``tile`` frame pixels, shuffled and offset at random every epoch, each batch taking its pixels'
    frames, the event pairs of the super pixels anchored in its tiles, and the TV pairs inside it."""

    preset: str = "fast"
    epochs: int = 50
    lr: float = 5e-3
    material_lr: float = 5e-2
    frame_weight: float = 1.0
    event_weight: float = 0.05
    tv_weight: float = 0.02
    tv_fraction: float = 0.3
    event_batch: int = 16384
    frame_samples: int = 0
    batch_pixels: int = 0
    tile: int = 8
    seed: int = 0


@dataclass
class Problem:
    """Everything a fit needs, as tensors on one device. P masked frame pixels (``pixels``, flat
    indices into the H×W frame grid); M importance frame samples (``sample_*``, empty when the frames
are integrated on a time grid shared by all pixels, ``shared_*``); E event pairs with F footprint
taps each."""

    height: int
    width: int
    frames: int
    pixels: np.ndarray
    albedo_scale: float
    coords: Tensor
    grid_shape: tuple[int, int]
    grid_taps: tuple[Tensor, Tensor]
    init_normal: Tensor
    init_albedo: Tensor
    sample_pixel: Tensor
    sample_group: Tensor
    sample_light: Tensor
    sample_weight: Tensor
    shared_light: Tensor | None
    shared_weight: Tensor | None
    shared_visible: Tensor | None
    measured: Tensor
    saturated: Tensor
    event_taps: Tensor
    event_tap_weight: Tensor
    event_light: Tensor
    event_light_ref: Tensor
    event_grey: Tensor
    event_grey_ref: Tensor
    event_target: Tensor
    event_weight: Tensor
    tv_pairs: Tensor
    view: Tensor
    shadow_fraction: np.ndarray
    diagnostics: dict[str, Any] = field(default_factory=dict)


def _positions(pixels: np.ndarray, size: int) -> np.ndarray:
    """Flat frame index → position among the masked pixels (−1 outside the mask)."""
    position = np.full(size, -1, dtype=np.int64)
    position[pixels] = np.arange(pixels.size)
    return position


def footprints(event_shape: tuple[int, int], frame_shape: tuple[int, int], event_scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Frame pixels under each event pixel of the grid ``psfmt.scale_affine(event_scale)``: (He·We, F)
    flat frame indices and area weights (the simulator's area average, ``pstoolkit.render.area_weights``)."""
    (he, we), (h, w) = event_shape, frame_shape
    rows = [area_weights(n_e, n_f, event_scale) for n_e, n_f in ((he, h), (we, w))]
    bands = []
    for weights in rows:
        taps = int((weights > 0).sum(axis=1).max())
        index = np.argsort(-weights, axis=1, kind="stable")[:, :taps]
        bands.append((index, np.take_along_axis(weights, index, axis=1)))
    (r_idx, r_w), (c_idx, c_w) = bands
    frame = (r_idx[:, None, :, None] * w + c_idx[None, :, None, :]).reshape(he * we, -1)
    weight = (r_w[:, None, :, None] * c_w[None, :, None, :]).reshape(he * we, -1)
    return frame, weight


def tv_pairs(mask: np.ndarray) -> np.ndarray:
    """(Q, 2) positions among the masked pixels of right and down neighbours that are both masked."""
    h, w = mask.shape
    position = _positions(np.flatnonzero(mask), h * w).reshape(h, w)
    right = np.stack([position[:, :-1].ravel(), position[:, 1:].ravel()], axis=1)
    down = np.stack([position[:-1, :].ravel(), position[1:, :].ravel()], axis=1)
    pairs = np.concatenate([right, down])
    return pairs[(pairs >= 0).all(axis=1)]


def albedo_scale(init_albedo: np.ndarray, mask: np.ndarray) -> float:
    grey = init_albedo[mask] @ np.asarray(GREY_WEIGHTS)
    grey = grey[np.isfinite(grey) & (grey > 0)]
    return float(np.percentile(grey, SCALE_PERCENTILE)) if grey.size else 1.0


def build_problem(pre: Any, view: np.ndarray, *, shadows: bool, device: str, frame_samples: int = 0,
                  dtype: torch.dtype = torch.float32) -> Problem:
    """Tensors of a fit from a ``preprocess.Preprocessed``: frame samples with their lights and
    weights (e·m_c·Δt·scale) — the importance samples, or ``frame_samples`` per frame on a shared
    midpoint grid — measured frames, event pairs with footprints, lights and targets."""
    h, w = pre.height, pre.width
    he, we = pre.event_height, pre.event_width
    mask = np.asarray(pre.mask, dtype=bool)
    pixels = np.flatnonzero(mask)
    p = pixels.size
    position = _positions(pixels, h * w)
    scale = albedo_scale(np.asarray(pre.init_albedo), mask)
    light = pre.light

    def tensor(array: np.ndarray, kind: torch.dtype = dtype) -> Tensor:
        return torch.as_tensor(np.ascontiguousarray(array), dtype=kind, device=device)

    k = int(pre.frames.shape[0])
    exposure_s = float(np.sum(np.asarray(pre.t_end_us) - np.asarray(pre.t_start_us))) / US_PER_S
    shared: tuple[np.ndarray, np.ndarray, np.ndarray | None] | None = None
    s_pos, s_frame, s_t, s_weight = np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3))
    if frame_samples > 0:
        t_start = np.asarray(pre.t_start_us, dtype=np.float64)
        t_end = np.asarray(pre.t_end_us, dtype=np.float64)
        g_t = np.concatenate([sample_times(t_start[j], t_end[j], frame_samples) for j in range(k)])
        g_dt = np.repeat((t_end - t_start) / frame_samples / US_PER_S, frame_samples)
        g_dir, g_int = light.evaluate(g_t)
        g_visible = None
        if shadows:
            g_visible = ~np.asarray(pre.in_shadow(np.repeat(pixels, g_t.size), np.tile(g_t, p)), dtype=bool).reshape(p, -1)
        shared = (g_dir, g_int * (g_dt * scale)[:, None], g_visible)
        lit_s = np.full(p, exposure_s) if g_visible is None else g_visible @ g_dt
    else:
        # The importance samples of eq. 21, fixed in preprocessing, which already left out the
        # samples in detected cast shadows.
        s_pixel = np.asarray(pre.frame_sample_pixel, dtype=np.int64)
        keep = position[s_pixel] >= 0
        s_pos = position[s_pixel[keep]]
        s_frame = np.asarray(pre.frame_sample_frame, dtype=np.int64)[keep]
        s_t = np.asarray(pre.frame_sample_t_us, dtype=np.float64)[keep]
        s_dt = np.asarray(pre.frame_sample_dt_s, dtype=np.float64)[keep]
        # grouped by pixel, so a mini-batch takes its pixels' samples as contiguous ranges
        order = np.argsort(s_pos, kind="stable")
        s_pos, s_frame, s_t, s_dt = s_pos[order], s_frame[order], s_t[order], s_dt[order]
        s_weight = light.evaluate(s_t)[1] * (s_dt * scale)[:, None]
        lit_s = np.bincount(s_pos, weights=s_dt, minlength=p)
    shadow_fraction = np.zeros(h * w)
    shadow_fraction[pixels] = np.clip(1.0 - lit_s / exposure_s, 0.0, 1.0)

    measured = np.asarray(pre.frames, dtype=np.float32).reshape(k, h * w, -1)[:, pixels].reshape(k * p, -1)
    saturated = np.asarray(pre.saturated, dtype=bool).reshape(k, h * w)[:, pixels].reshape(k * p)

    # Event pairs (eq. 25) with the frame pixels under their super pixel.
    scale_e = float(we) / float(w)
    fp_frame, fp_weight = footprints((he, we), (h, w), scale_e)
    e_pixel = np.asarray(pre.event_pixel, dtype=np.int64)
    taps = position[fp_frame[e_pixel]]
    tap_weight = np.where(taps >= 0, fp_weight[e_pixel], 0.0)
    t_ev = np.asarray(pre.event_t_us, dtype=np.float64)
    t_ref = np.asarray(pre.event_t_ref_us, dtype=np.float64)
    usable = tap_weight.sum(axis=1) > 0
    if shadows and e_pixel.size:
        frame_taps = fp_frame[e_pixel]
        n_taps = frame_taps.shape[1]
        lit = ~np.asarray(pre.in_shadow(frame_taps.ravel(), np.repeat(t_ev, n_taps)), dtype=bool)
        lit &= ~np.asarray(pre.in_shadow(frame_taps.ravel(), np.repeat(t_ref, n_taps)), dtype=bool)
        # A pair with a shadow edge between its two times breaks the shadow-free ratio: drop it.
        usable &= np.all(lit.reshape(-1, n_taps) | (tap_weight <= 0), axis=1)
    polarity = np.asarray(pre.event_polarity, dtype=np.float64)
    contrast = np.where(polarity > 0, pre.contrast_pos, pre.contrast_neg)
    alpha = np.asarray(pre.event_alpha, dtype=np.float64)
    target = np.log(np.clip(alpha, 1e-6, None)) + polarity * contrast
    weight = np.asarray(pre.event_weight, dtype=np.float64)
    usable &= weight > 0
    dir_ev, int_ev = light.evaluate(t_ev[usable])
    dir_ref, int_ref = light.evaluate(t_ref[usable])
    grey_w = np.asarray(GREY_WEIGHTS)

    v, u = np.divmod(pixels, w)
    ue, ve = frame_to_event(pre.event_to_frame, u.astype(np.float64), v.astype(np.float64))
    grid_index, grid_weight = bilinear_taps(ue, ve, we, he)

    init_normal = np.asarray(pre.init_normal, dtype=np.float64).reshape(h * w, 3)[pixels]
    bad = ~np.isfinite(init_normal).all(axis=1) | (np.linalg.norm(init_normal, axis=1) < 0.5)
    init_normal[bad] = (0.0, 0.0, 1.0)
    init_albedo = np.asarray(pre.init_albedo, dtype=np.float64).reshape(h * w, -1)[pixels] / scale
    init_albedo = np.where(np.isfinite(init_albedo), init_albedo, 1.0)
    coords = np.stack([2.0 * u / max(w - 1, 1) - 1.0, 1.0 - 2.0 * v / max(h - 1, 1)], axis=1)

    return Problem(
        height=h, width=w, frames=k, pixels=pixels, albedo_scale=scale,
        coords=tensor(coords), grid_shape=(he, we),
        grid_taps=(tensor(grid_index, torch.int64), tensor(grid_weight)),
        init_normal=tensor(init_normal), init_albedo=tensor(init_albedo),
        sample_pixel=tensor(s_pos, torch.int64), sample_group=tensor(s_frame * p + s_pos, torch.int64),
        sample_light=tensor(light.evaluate(s_t)[0] if s_t.size else np.zeros((0, 3))), sample_weight=tensor(s_weight),
        shared_light=None if shared is None else tensor(shared[0]),
        shared_weight=None if shared is None else tensor(shared[1]),
        shared_visible=None if shared is None or shared[2] is None else tensor(shared[2]),
        measured=tensor(measured), saturated=tensor(saturated, torch.bool),
        event_taps=tensor(np.maximum(taps[usable], 0), torch.int64), event_tap_weight=tensor(tap_weight[usable]),
        event_light=tensor(dir_ev), event_light_ref=tensor(dir_ref),
        event_grey=tensor(int_ev * grey_w), event_grey_ref=tensor(int_ref * grey_w),
        event_target=tensor(target[usable]), event_weight=tensor(weight[usable]),
        tv_pairs=tensor(tv_pairs(mask), torch.int64),
        view=tensor(np.asarray(view, dtype=np.float64)),
        shadow_fraction=shadow_fraction.reshape(h, w),
        diagnostics={
            "pixels": int(p), "frame_samples": int(s_pos.size) if shared is None else int(p * shared[0].shape[0]), "event_pairs": int(usable.sum()),
            "event_pairs_dropped": int(e_pixel.size - usable.sum()), "albedo_scale": scale,
            "cast_shadow_share": float(shadow_fraction[pixels].mean()) if p else 0.0,
        },
    )


def build_field(problem: Problem, reflectance: Reflectance, preset: str) -> nn.Module:
    """``fast`` → GridField from the closed-form initialisation; ``paper`` → the paper's NeuralField."""
    material_init = reflectance.raw_init().to(problem.coords.device, problem.coords.dtype)
    if preset == "paper":
        return NeuralField(problem.coords, reflectance.channels, material_init).to(problem.coords.device)
    return GridField(problem.init_normal, problem.init_albedo, problem.grid_shape, problem.grid_taps, material_init)


def _optimizer(field: nn.Module, reflectance: Reflectance, config: TrainConfig) -> torch.optim.Optimizer:
    if isinstance(field, GridField):
        groups = [
            {"params": [field.normal, field.log_albedo], "lr": config.lr},
            {"params": [field.grid, *reflectance.parameters()], "lr": config.material_lr},
        ]
    else:
        groups = [{"params": [*field.parameters(), *reflectance.parameters()], "lr": config.lr}]
    return torch.optim.Adam(groups)


@dataclass
class Batch:
    """One Adam step's share of the problem. ``pixels`` (N,) the masked-pixel positions the field
    is evaluated at (None: all, in order), the first ``frame_pixels`` of them (None: all) the pixels
    whose frames are fitted; ``frame_rows`` their rows of ``Problem.measured`` in frame-major order
    (None: all); ``samples`` their importance samples (None: all) with ``sample_pixel`` and
    ``sample_group`` (frame·frame_pixels + pixel) in local positions; ``events`` the event pairs
    with ``event_taps`` in local positions; ``tv_pairs`` local neighbour pairs."""

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
                 sample_pixel=problem.sample_pixel, sample_group=problem.sample_group,
                 events=events, event_taps=problem.event_taps[events], tv_pairs=problem.tv_pairs)


@dataclass
class Tiling:
    """What ``mini_batches`` needs of a problem, as numpy: each masked pixel's (row, column), each
    event pair's anchor pixel (its footprint's largest tap) and taps, the importance samples'
    per-pixel ranges and frames, and the TV pairs."""

    row: np.ndarray
    col: np.ndarray
    event_anchor: np.ndarray
    event_taps: np.ndarray
    sample_start: np.ndarray
    sample_count: np.ndarray
    sample_frame: np.ndarray
    tv_pairs: np.ndarray

    @classmethod
    def of(cls, problem: Problem) -> Tiling:
        p = problem.pixels.size
        row, col = np.divmod(problem.pixels, problem.width)
        taps = problem.event_taps.cpu().numpy()
        anchor = taps[np.arange(len(taps)), np.argmax(problem.event_tap_weight.cpu().numpy(), axis=1)] if taps.size else np.zeros(0, np.int64)
        sample_pixel = problem.sample_pixel.cpu().numpy()
        count = np.bincount(sample_pixel, minlength=p)
        return cls(row=row, col=col, event_anchor=anchor, event_taps=taps,
                   sample_start=np.cumsum(count) - count, sample_count=count,
                   sample_frame=problem.sample_group.cpu().numpy() // max(p, 1),
                   tv_pairs=problem.tv_pairs.cpu().numpy())


def _ranges(start: np.ndarray, count: np.ndarray) -> np.ndarray:
    """The concatenated index ranges [start_i, start_i + count_i)."""
    total = int(count.sum())
    offsets = np.repeat(start - (np.cumsum(count) - count), count)
    return np.arange(total, dtype=np.int64) + offsets


def mini_batches(problem: Problem, tiling: Tiling, config: TrainConfig, generator: torch.Generator) -> list[Batch]:
    """One epoch's mini-batches (see ``TrainConfig``): a random tiling offset, tiles in random order
    grouped into batches of about ``config.batch_pixels`` pixels."""
    tile = config.tile
    p = problem.pixels.size
    shift = torch.randint(0, tile, (2,), generator=generator).numpy()
    rows = (problem.height + tile) // tile + 1
    cols = (problem.width + tile) // tile + 1
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
    device = problem.coords.device
    out = []
    for b in range(n_batches):
        own = by_pixel[pixel_bounds[b]:pixel_bounds[b + 1]]
        events = by_event[event_bounds[b]:event_bounds[b + 1]]
        taps = tiling.event_taps[events]
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
            frame_rows=tensor((np.arange(problem.frames)[:, None] * p + own[None, :]).ravel()),
            samples=tensor(samples), sample_pixel=tensor(sample_pixel),
            sample_group=tensor(tiling.sample_frame[samples] * n + sample_pixel),
            events=tensor(events), event_taps=tensor(local[taps]), tv_pairs=tensor(local[pairs]),
        ))
        local[pixels] = -1
    return out


def losses(problem: Problem, field: nn.Module, reflectance: Reflectance, config: TrainConfig,
           batch: Batch, tv_share: float) -> tuple[Tensor, dict[str, float]]:
    """The total loss of eq. 26 and its parts on ``batch`` for the current parameters."""
    normal, albedo, raw = field(batch.pixels)
    n = batch.frame_pixels
    own = (normal, albedo, raw) if n is None else (normal[:n], albedo[:n], raw[:n])
    if problem.shared_light is not None:
        visible = problem.shared_visible
        if visible is not None and batch.pixels is not None:
            visible = visible[batch.pixels[:n]]
        predicted = frame_prediction_grid(reflectance, *own, problem.shared_light, problem.shared_weight,
                                          visible, problem.view, problem.frames)
    else:
        light, weight = problem.sample_light, problem.sample_weight
        if batch.samples is not None:
            light, weight = light[batch.samples], weight[batch.samples]
        predicted = frame_prediction(reflectance, *own, batch.sample_pixel, batch.sample_group, light, weight,
                                     problem.view, problem.frames * own[0].shape[0])
    measured, saturated = problem.measured, problem.saturated
    if batch.frame_rows is not None:
        measured, saturated = measured[batch.frame_rows], saturated[batch.frame_rows]
    lf = frame_loss(predicted, measured, saturated)
    total = config.frame_weight * lf
    parts = {"frame": float(lf.detach())}
    e = batch.events
    if e.numel() and config.event_weight > 0:
        tap_w = problem.event_tap_weight[e]
        grey = superpixel_grey(reflectance, normal, albedo, raw, batch.event_taps, tap_w,
                               problem.event_light[e], problem.event_grey[e], problem.view)
        grey_ref = superpixel_grey(reflectance, normal, albedo, raw, batch.event_taps, tap_w,
                                   problem.event_light_ref[e], problem.event_grey_ref[e], problem.view)
        le = event_loss(grey, grey_ref, problem.event_target[e], problem.event_weight[e], LOG_EPS)
        total = total + config.event_weight * le
        parts["event"] = float(le.detach())
    if tv_share > 0 and config.tv_weight > 0:
        ltv = tv_loss(normal, batch.tv_pairs) + tv_loss(albedo, batch.tv_pairs)
        total = total + config.tv_weight * tv_share * ltv
        parts["tv"] = float(ltv.detach())
    return total, parts


def _event_sample(problem: Problem, config: TrainConfig, generator: torch.Generator) -> Tensor:
    n_events = problem.event_target.numel()
    if 0 < config.event_batch < n_events:
        index = torch.randperm(n_events, generator=generator)[: config.event_batch]
    else:
        index = torch.arange(n_events)
    return index.to(problem.event_target.device)


def train(problem: Problem, field: nn.Module, reflectance: Reflectance, config: TrainConfig,
          progress: Progress) -> list[dict[str, float]]:
    """Adam over ``config.epochs`` epochs; returns the loss parts (means over the epoch's batches)
    of every PROGRESS_EVERY-th epoch."""
    generator = torch.Generator(device="cpu").manual_seed(config.seed)
    optimizer = _optimizer(field, reflectance, config)
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
        for batch in batches:
            loss, parts = losses(problem, field, reflectance, config, batch, max(0.0, 1.0 - epoch / warmup))
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            for name, value in {"loss": float(loss.detach()), **parts}.items():
                totals[name] = totals.get(name, 0.0) + value / len(batches)
        scheduler.step()
        if epoch % PROGRESS_EVERY == 0 or epoch == config.epochs - 1:
            history.append({"epoch": float(epoch), "steps": float(len(batches)), **totals})
            progress((epoch + 1) / config.epochs, f"epoch {epoch + 1}/{config.epochs} loss {totals['loss']:.4g}")
    return history
