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
from pstoolkit_dualres.losses import event_loss, frame_loss, tv_loss
from pstoolkit_dualres.model import GridField, NeuralField, bilinear_taps
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
    """Hyper-parameters of one fit: ``epochs`` full passes (one Adam step each), learning rates of the
    normal/albedo parameters (``lr``) and of the materials (``material_lr``), the loss weights λ_f,
    λ_e, λ_tv of eq. 26 with the TV term fading linearly to zero over the first ``tv_fraction`` of
    the epochs, ``event_batch`` event pairs drawn per epoch (0 = all), and ``frame_samples`` per frame
on a time grid shared by all pixels (0 = the importance samples of preprocessing)."""

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

    a = np.asarray(pre.event_to_frame, dtype=np.float64)
    v, u = np.divmod(pixels, w)
    ue, ve = np.linalg.solve(a[:, :2], np.stack([u - a[0, 2], v - a[1, 2]]))
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


def losses(problem: Problem, field: nn.Module, reflectance: Reflectance, config: TrainConfig,
           event_index: Tensor | None, tv_share: float) -> tuple[Tensor, dict[str, float]]:
    """The total loss of eq. 26 and its parts for the current parameters."""
    normal, albedo, raw = field()
    if problem.shared_light is not None:
        predicted = frame_prediction_grid(
            reflectance, normal, albedo, raw, problem.shared_light, problem.shared_weight,
            problem.shared_visible, problem.view, problem.frames,
        )
    else:
        predicted = frame_prediction(
            reflectance, normal, albedo, raw, problem.sample_pixel, problem.sample_group,
            problem.sample_light, problem.sample_weight, problem.view, problem.frames * problem.pixels.size,
        )
    lf = frame_loss(predicted, problem.measured, problem.saturated)
    total = config.frame_weight * lf
    parts = {"frame": float(lf.detach())}
    if event_index is not None and event_index.numel() and config.event_weight > 0:
        taps, tap_w = problem.event_taps[event_index], problem.event_tap_weight[event_index]
        grey = superpixel_grey(reflectance, normal, albedo, raw, taps, tap_w,
                               problem.event_light[event_index], problem.event_grey[event_index], problem.view)
        grey_ref = superpixel_grey(reflectance, normal, albedo, raw, taps, tap_w,
                                   problem.event_light_ref[event_index], problem.event_grey_ref[event_index], problem.view)
        le = event_loss(grey, grey_ref, problem.event_target[event_index], problem.event_weight[event_index], LOG_EPS)
        total = total + config.event_weight * le
        parts["event"] = float(le.detach())
    if tv_share > 0 and config.tv_weight > 0:
        ltv = tv_loss(normal, problem.tv_pairs) + tv_loss(albedo, problem.tv_pairs)
        total = total + config.tv_weight * tv_share * ltv
        parts["tv"] = float(ltv.detach())
    return total, parts


def train(problem: Problem, field: nn.Module, reflectance: Reflectance, config: TrainConfig,
          progress: Progress) -> list[dict[str, float]]:
    """Adam over ``config.epochs`` epochs; returns the loss parts of every PROGRESS_EVERY-th epoch."""
    generator = torch.Generator(device="cpu").manual_seed(config.seed)
    optimizer = _optimizer(field, reflectance, config)
    scheduler = torch.optim.lr_scheduler.ExponentialLR(optimizer, LR_DECAY ** (1.0 / max(config.epochs, 1)))
    n_events = problem.event_target.numel()
    history: list[dict[str, float]] = []
    warmup = max(config.tv_fraction * config.epochs, 1e-9)
    for epoch in range(config.epochs):
        event_index = None
        if n_events:
            if 0 < config.event_batch < n_events:
                event_index = torch.randperm(n_events, generator=generator)[: config.event_batch]
            else:
                event_index = torch.arange(n_events)
            event_index = event_index.to(problem.event_target.device)
        loss, parts = losses(problem, field, reflectance, config, event_index, max(0.0, 1.0 - epoch / warmup))
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        scheduler.step()
        if epoch % PROGRESS_EVERY == 0 or epoch == config.epochs - 1:
            parts = {"epoch": float(epoch), "loss": float(loss.detach()), **parts}
            history.append(parts)
            progress((epoch + 1) / config.epochs, f"epoch {epoch + 1}/{config.epochs} loss {parts['loss']:.4g}")
    return history
