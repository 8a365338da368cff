"""A preprocessed capture as tensors on one device (``build_problem``), and the cast-shadow mask
applied to it (``Problem.apply_mask``; on a device that is not the CPU its lookups run there,
``table_device``).

A ``Problem`` is three parts and the units they share: the masked pixel grid the fit lives on with
its start values (``Geometry``), the frame term of eq. 24 (``FrameTerms``) and the event term of
eq. 25 (``EventTerms``). The mask changes only the last two, each from numpy copies of its own.

Units: frame values in units of saturation; radiometric maps (albedo, F0) in units of
``albedo_scale`` (a bright albedo of the capture, in frame units per unit light per second), which
the frame sample weights carry; the event irradiance is e·f_r·[n·l]₊ in those units, so a bright lit
pixel is ≈ 1 as the event model's ε assumes (``pstoolkit.events.rule``).

The mask m_c enters all three places the paper names (eq. 14, 21–22, 25): the closed-form start
(``preprocess.Preprocessed.closed_form``), the frames — each frame sample of the shared time grid is
weighted by the lit share of its sub-interval, an importance sample by whether it is lit — and the
events, whose super-pixel irradiance sums only the lit frame pixels under it at each end of a pair;
a pair across which any of them enters or leaves a shadow is left out (the sensor saw the edge, not
the shading).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from pstoolkit import GREY_WEIGHTS, US_PER_S, ShadowMask
from pstoolkit._shared import devices
from pstoolkit.grid import affine_footprints, bilinear_taps, frame_to_event
from pstoolkit.optics.equivalent import sample_times
from pstoolkit.shadows.table_device import DeviceShadowMask
from pstoolkit_dualres.closed_form import ClosedFormStart
from pstoolkit_dualres.preprocess import Preprocessed

# Percentile of the initial grey albedo over the mask taken as the albedo scale: a bright albedo
# that ignores the few outliers of the closed form near the terminator.
SCALE_PERCENTILE = 95.0
# A super pixel counts as inside the frame when this little of its area is outside (float sums of
# the footprint's shares).
INSIDE_TOLERANCE = 1e-6
# Midpoints per frame window of the light energy indirect light is reflected under (the intensity
# changes slowly along a turn: 64 points integrate it to far below a frame's quantisation).
ENERGY_SAMPLES = 64


def _like(array: np.ndarray, reference: Tensor) -> Tensor:
    """``array`` as a tensor of ``reference``'s dtype on its device."""
    return torch.as_tensor(np.ascontiguousarray(array), dtype=reference.dtype, device=reference.device)


@dataclass
class Geometry:
    """The P masked frame pixels a fit solves for, and where it starts. ``pixels`` (P,) flat indices
    into the ``height``×``width`` frame grid; ``coords`` (P, 2) their positions in [−1, 1] (x right,
    y up), the network's input; ``grid_taps`` (P, 4) int64 indices into the ``event_shape`` (He, We)
    event grid and (P, 4) bilinear weights, where a frame pixel reads the smooth materials;
    ``tv_pairs`` (Q, 2) int64 positions among the P of right and down neighbours both masked;
    ``view`` (3,) direction towards the camera; ``init_normal`` (P, 3) start normals (the closed
    form's, facing the camera where it has none) and ``init_albedo`` (P, 3) start albedo in units of
    the albedo scale."""

    height: int
    width: int
    pixels: np.ndarray
    coords: Tensor
    event_shape: tuple[int, int]
    grid_taps: tuple[Tensor, Tensor]
    tv_pairs: Tensor
    view: Tensor
    init_normal: Tensor
    init_albedo: Tensor


@dataclass
class FrameTerms:
    """The K = ``count`` measured frames and how the fit predicts them, as one of two kinds of sample:

    - S samples per frame on a time grid shared by all pixels (``shared_*``, None otherwise):
      ``shared_light`` (K·S, 3) unit light directions in frame order, ``shared_weight`` (K·S, 3) RGB
      intensity × Δt (s) × albedo scale, ``shared_visible`` (K·S, P) the lit share of each sample's
      sub-interval under the mask (None without one);
    - M importance samples grouped by pixel (``sample_*``, empty with the shared grid):
      ``sample_pixel`` (M,) int64 position among the P, ``sample_group`` (M,) int64
      frame·P + position, ``sample_light`` (M, 3) unit directions, ``sample_weight`` (M, 3) RGB
      intensity × Δt (s) × albedo scale × lit (0 or 1 under the mask).

    ``measured`` (K·P, 3) frame values in units of saturation and ``saturated`` (K·P,) bool, rows in
    frame-major order; ``exposure_s`` the K frames' summed exposure time; ``energy`` (K, 3) each
    frame's ∫ e dt × albedo scale over its window, no mask applied (what indirect light is reflected
    under). ``source`` holds the numpy
    copies the mask is applied from: ``shared_t``/``shared_dt_us`` (K·S,) µs, or ``sample_t`` (M,) µs,
    ``sample_dt_s`` (M,) s and ``sample_weight`` (M, 3) without the mask; and ``measured`` as built
    once ``apply_bounce`` has changed it. ``source_there``: those the mask reads, as tensors on a
    device that is not the CPU, moved the first time a mask is applied there."""

    count: int
    exposure_s: float
    shared_light: Tensor | None
    shared_weight: Tensor | None
    shared_visible: Tensor | None
    sample_pixel: Tensor
    sample_group: Tensor
    sample_light: Tensor
    sample_weight: Tensor
    measured: Tensor
    saturated: Tensor
    energy: Tensor
    source: dict[str, np.ndarray] = field(default_factory=dict, repr=False)
    source_there: dict[str, Tensor] = field(default_factory=dict, repr=False)

    def apply_mask(self, shadows: ShadowMask | DeviceShadowMask, pixels: np.ndarray) -> np.ndarray:
        """Weigh the samples by what ``shadows`` leaves lit at ``pixels`` (P,); returns (P,) the
        exposure time in shadow, s. A ``DeviceShadowMask`` is applied on the device
        (``_apply_mask_there``)."""
        if isinstance(shadows, DeviceShadowMask):
            return self._apply_mask_there(shadows, pixels)
        src = self.source
        if "shared_t" in src:
            t, half = src["shared_t"], 0.5 * src["shared_dt_us"]
            shadowed = shadows.shadowed_grid(pixels, t - half, t + half)
            visible = np.clip(1.0 - shadowed / (2.0 * half[:, None]), 0.0, 1.0)
            # no mask, no (K·S, P) product in every step
            self.shared_visible = _like(visible, self.measured) if len(shadows) else None
            return (2.0 * half) @ (1.0 - visible) / US_PER_S
        lit = ~shadows.contains(pixels[src["sample_pixel"]], src["sample_t"])
        self.sample_weight = _like(src["sample_weight"] * lit[:, None], self.measured)
        return np.bincount(src["sample_pixel"], weights=src["sample_dt_s"] * ~lit, minlength=pixels.size)

    def _apply_mask_there(self, shadows: DeviceShadowMask, pixels: np.ndarray) -> np.ndarray:
        """``apply_mask``'s expressions in torch, from ``source`` moved to the device once."""
        src = _on_device(self.source_there, self.source, ("shared_t", "shared_dt_us", "sample_t", "sample_dt_s",
                                                          "sample_weight"), shadows.device)
        on = torch.as_tensor(pixels, dtype=torch.int64, device=shadows.device)
        if "shared_t" in src:
            t, half = src["shared_t"], 0.5 * src["shared_dt_us"]
            shadowed = shadows.shadowed_grid(on, t - half, t + half)
            visible = torch.clamp(1.0 - shadowed / (2.0 * half[:, None]), 0.0, 1.0)
            self.shared_visible = visible.to(self.measured.dtype) if len(shadows) else None
            return ((2.0 * half) @ (1.0 - visible) / US_PER_S).cpu().numpy()
        lit = ~shadows.contains(on[self.sample_pixel], src["sample_t"])
        self.sample_weight = (src["sample_weight"] * lit[:, None]).to(self.measured.dtype)
        shadowed_s = torch.zeros(pixels.size, dtype=torch.float64, device=shadows.device)
        return shadowed_s.index_add_(0, self.sample_pixel, src["sample_dt_s"] * ~lit).cpu().numpy()

    def apply_bounce(self, offset: np.ndarray) -> np.ndarray:
        """Set ``measured`` to the frames as built minus ``offset`` (K·P, 3), the light inter-reflection
        adds (``interreflection.frame_offsets``); returns the frames as built."""
        built = self.source.setdefault("measured", self.measured.detach().cpu().numpy().copy())
        self.measured = _like(built - offset, self.measured)
        return built


@dataclass
class EventTerms:
    """E event pairs (``pairs.EventSamples``), each seen through the F frame pixels under its super
    pixel. ``taps`` (E, F) int64 positions among the P masked pixels (0 on a tap outside the mask,
    whose weight is 0); ``tap_weight_now``/``tap_weight_ref`` (E, F) each tap's area share, 0 where
    the mask shadows it at the pair's later (``t_us``) or earlier (``t_ref_us``) time; ``light_now``/
    ``light_ref`` (E, 3) unit light directions, ``tap_area`` (E, F) each tap's area share without the
    mask (what indirect light reaches), ``grey_now``/``grey_ref`` (E, 3) RGB intensity ×
    Rec. 601 weight at those times; ``target`` (E,) the log-irradiance step between them and
    ``weight`` (E,) its confidence ≥ 0; ``usable`` (U,) int64 the pairs the loss may draw under the
    current mask. ``source`` holds the numpy copies the mask is applied from: ``frame_taps`` (E, F)
    flat frame indices, ``area`` (E, F), ``t_us``/``t_ref_us`` (E,) µs and ``usable`` (E,) bool
    without a mask, ``pixel`` (E,) each pair's event pixel with ``weight`` (E,) its confidence
    before any ``apply_gate``, and ``rise``/``fall`` (E,) the nominal thresholds of its positive and
    negative events (``target`` = rise − fall until ``apply_thresholds``); the three ``apply_`` methods
    after the mask keep what they set there (``steps``, ``gate``, ``bounce_*``), so that each composes
    with the others. ``source_there``: what the mask reads of ``source``, as tensors on a device that
    is not the CPU, moved the first time a mask is applied there."""

    taps: Tensor
    tap_weight_now: Tensor
    tap_weight_ref: Tensor
    light_now: Tensor
    light_ref: Tensor
    tap_area: Tensor
    grey_now: Tensor
    grey_ref: Tensor
    target: Tensor
    weight: Tensor
    usable: Tensor
    source: dict[str, np.ndarray] = field(default_factory=dict, repr=False)
    source_there: dict[str, Tensor] = field(default_factory=dict, repr=False)

    def apply_mask(self, shadows: ShadowMask | DeviceShadowMask) -> None:
        """Keep each tap's area only where ``shadows`` leaves it lit, and only the pairs across which
        no tap enters or leaves a shadow and some area stays lit at both ends. A ``DeviceShadowMask``
        is applied on the device (``_apply_mask_there``)."""
        if isinstance(shadows, DeviceShadowMask):
            self._apply_mask_there(shadows)
            return
        src = self.source
        taps, area, t_now, t_ref = src["frame_taps"], src["area"], src["t_us"], src["t_ref_us"]
        n_taps = taps.shape[1]
        flat, now, ref = taps.ravel(), np.repeat(t_now, n_taps), np.repeat(t_ref, n_taps)
        lit_now = ~shadows.contains(flat, now).reshape(taps.shape)
        lit_ref = ~shadows.contains(flat, ref).reshape(taps.shape)
        in_between = shadows.shadowed_us(flat, ref, now).reshape(taps.shape)
        steady = (in_between <= 0.0) | (in_between >= (t_now - t_ref)[:, None])
        weight_now, weight_ref = area * lit_now, area * lit_ref
        usable = src["usable"] & np.all(steady | (area <= 0), axis=1)
        usable &= (weight_now.sum(axis=1) > 0) & (weight_ref.sum(axis=1) > 0)
        self.tap_weight_now = _like(weight_now, self.target)
        self.tap_weight_ref = _like(weight_ref, self.target)
        self.usable = torch.as_tensor(np.flatnonzero(usable), dtype=torch.int64, device=self.target.device)

    def _apply_mask_there(self, shadows: DeviceShadowMask) -> None:
        """``apply_mask``'s expressions in torch, from ``source`` moved to the device once."""
        src = _on_device(self.source_there, self.source, ("frame_taps", "area", "t_us", "t_ref_us", "usable"), shadows.device)
        taps, area, t_now, t_ref = src["frame_taps"], src["area"], src["t_us"][:, None], src["t_ref_us"][:, None]
        lit_now, lit_ref = ~shadows.contains(taps, t_now), ~shadows.contains(taps, t_ref)
        in_between = shadows.shadowed_us(taps, t_ref, t_now)
        steady = (in_between <= 0.0) | (in_between >= t_now - t_ref)
        weight_now, weight_ref = area * lit_now, area * lit_ref
        usable = src["usable"] & torch.all(steady | (area <= 0), dim=1)
        usable &= (weight_now.sum(dim=1) > 0) & (weight_ref.sum(dim=1) > 0)
        self.tap_weight_now = weight_now.to(self.target.dtype)
        self.tap_weight_ref = weight_ref.to(self.target.dtype)
        self.usable = torch.nonzero(usable).reshape(-1)

    @property
    def pixel(self) -> np.ndarray:
        """(E,) int64 the event pixel of each pair."""
        return self.source["pixel"]

    def apply_thresholds(self, gain_pos: np.ndarray, gain_neg: np.ndarray) -> None:
        """Set each pair's ``target`` to its positive events' thresholds times its event pixel's entry
        of ``gain_pos`` (He·We,) minus its negative ones' times that of ``gain_neg``
        (``thresholds.fit_thresholds``)."""
        src, pixel = self.source, self.source["pixel"]
        src["steps"] = src["rise"] * gain_pos[pixel] - src["fall"] * gain_neg[pixel]
        self._set_targets()

    def apply_gate(self, pixel_weight: np.ndarray) -> None:
        """Weigh each pair's confidence by its event pixel's entry of ``pixel_weight`` (He·We,)
        (``consistency.event_gate``), from the confidences the pairs were built with."""
        self.source["gate"] = pixel_weight[self.pixel]
        self._set_weights()

    def apply_bounce(self, shift: np.ndarray, keep: np.ndarray, bounce_now: np.ndarray, bounce_ref: np.ndarray) -> None:
        """Add ``shift`` (E,) to each pair's log step and leave out the pairs not in ``keep`` (E,) bool:
        what inter-reflection changes of the direct shading's steps (``interreflection.remove_bounce``);
        ``bounce_now``/``bounce_ref`` (E,) the bounce's grey irradiance at its two times, kept for
        ``interreflection.unexplained``. Zero shifts, all kept and no bounce undo it."""
        src = self.source
        src["bounce_shift"], src["bounce_keep"], src["bounce_now"], src["bounce_ref"] = shift, keep, bounce_now, bounce_ref
        self._set_targets()
        self._set_weights()

    def measured_steps(self) -> np.ndarray:
        """(E,) each pair's log step as its events and thresholds give it, before a bounce shifts it."""
        src = self.source
        return src["steps"] if "steps" in src else src["rise"] - src["fall"]

    def gated_weight(self) -> np.ndarray:
        """(E,) each pair's confidence times its gate, before a bounce leaves any pair out."""
        src = self.source
        return src["weight"] * src.get("gate", 1.0)

    def _set_targets(self) -> None:
        self.target = _like(self.measured_steps() + self.source.get("bounce_shift", 0.0), self.target)

    def _set_weights(self) -> None:
        self.weight = _like(self.gated_weight() * self.source.get("bounce_keep", 1.0), self.weight)


@dataclass
class Problem:
    """Everything a fit needs, as tensors on one device: the pixel grid and start (``geometry``), the
    frame and event terms (``frames``, ``events``), the ``albedo_scale`` the radiometric values are
    in units of, ``shadow_fraction`` (H, W) the share of each pixel's exposure time the current mask
    removes, and ``diagnostics`` of the setup (pixels, samples, usable pairs, shadowed share)."""

    geometry: Geometry
    frames: FrameTerms
    events: EventTerms
    albedo_scale: float
    shadow_fraction: np.ndarray
    diagnostics: dict[str, Any] = field(default_factory=dict)

    @property
    def device(self) -> torch.device:
        return self.geometry.coords.device

    @property
    def dtype(self) -> torch.dtype:
        return self.geometry.coords.dtype

    def apply_mask(self, shadows: ShadowMask) -> None:
        """Take the cast-shadow mask ``shadows`` into the frame weights and the event pairs."""
        geometry = self.geometry
        pixels = geometry.pixels
        # on a device the lookups run there, the table moved once for both terms
        lookups = shadows if devices.on_host(self.device) else DeviceShadowMask(shadows, self.device)
        shadowed_s = self.frames.apply_mask(lookups, pixels)
        self.shadow_fraction = np.zeros(geometry.height * geometry.width)
        self.shadow_fraction[pixels] = np.clip(shadowed_s / self.frames.exposure_s, 0.0, 1.0)
        self.shadow_fraction = self.shadow_fraction.reshape(geometry.height, geometry.width)
        self.events.apply_mask(lookups)
        usable = self.events.usable.numel()
        total = self.events.target.shape[0]
        self.diagnostics.update(event_pairs=usable, event_pairs_dropped=total - usable,
                                cast_shadow_share=float(self.shadow_fraction.ravel()[pixels].mean()) if pixels.size else 0.0)


def _on_device(there: dict[str, Tensor], source: dict[str, np.ndarray], names: tuple[str, ...], device: torch.device
               ) -> dict[str, Tensor]:
    """``there``, filled the first time with the ``names`` of ``source`` it has, as tensors on ``device``
    (float64, int64 and bool as they are)."""
    if not there:
        there.update({name: torch.as_tensor(np.ascontiguousarray(source[name]), device=device) for name in names if name in source})
    return there


def _positions(pixels: np.ndarray, size: int) -> np.ndarray:
    """Flat frame index → position among the masked pixels (−1 outside the mask)."""
    position = np.full(size, -1, dtype=np.int64)
    position[pixels] = np.arange(pixels.size)
    return position


def tv_pairs(mask: np.ndarray) -> np.ndarray:
    """(Q, 2) positions among the masked pixels of right and down neighbours that are both masked."""
    h, w = mask.shape
    position = _positions(np.flatnonzero(mask), h * w).reshape(h, w)
    right = np.stack([position[:, :-1].ravel(), position[:, 1:].ravel()], axis=1)
    down = np.stack([position[:-1, :].ravel(), position[1:, :].ravel()], axis=1)
    pairs = np.concatenate([right, down])
    return pairs[(pairs >= 0).all(axis=1)]


def albedo_scale(init_albedo: np.ndarray, mask: np.ndarray) -> float:
    """The SCALE_PERCENTILE-th percentile of the grey (H, W, 3) ``init_albedo`` over ``mask`` (1 if
    it has no finite positive value)."""
    grey = init_albedo[mask] @ np.asarray(GREY_WEIGHTS)
    grey = grey[np.isfinite(grey) & (grey > 0)]
    return float(np.percentile(grey, SCALE_PERCENTILE)) if grey.size else 1.0


def build_problem(pre: Preprocessed, view: np.ndarray, *, device: str, frame_samples: int = 0, init: ClosedFormStart | None = None,
                  dtype: torch.dtype = torch.float32) -> Problem:
    """Tensors of a fit from a preprocessed capture, without a cast-shadow mask (``Problem.apply_mask``
    adds one): frame samples, measured frames, event pairs with footprints, lights and targets, and the
    start values.

    Parameters
    ----------
    pre
        The preprocessed capture.
    view
        (3,) unit direction towards the camera.
    device
        The torch device of the tensors.
    frame_samples
        Samples per frame of a shared midpoint grid; 0: the importance samples of preprocessing.
    init
        The start normals and albedo (default: ``pre.init``, the closed form without a mask).
    dtype
        The float dtype of the tensors.

    Returns
    -------
    Problem
        Radiometric values in units of ``albedo_scale``, the SCALE_PERCENTILE-th percentile of the
        start's grey albedo.
    """
    init = pre.init if init is None else init
    h, w = pre.height, pre.width
    he, we = pre.event_height, pre.event_width
    mask = np.asarray(pre.mask, dtype=bool)
    pixels = np.flatnonzero(mask)
    p = pixels.size
    position = _positions(pixels, h * w)
    scale = albedo_scale(np.asarray(init.albedo), mask)
    light = pre.light

    def tensor(array: np.ndarray, kind: torch.dtype = dtype) -> Tensor:
        return torch.as_tensor(np.ascontiguousarray(array), dtype=kind, device=device)

    k = int(pre.frames.shape[0])
    t_start = np.asarray(pre.t_start_us, dtype=np.float64)
    t_end = np.asarray(pre.t_end_us, dtype=np.float64)
    exposure_s = float(np.sum(t_end - t_start) / US_PER_S)
    frame_source: dict[str, np.ndarray] = {}
    shared_light = shared_weight = None
    s_pos, s_frame, s_dir, s_weight = np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3))
    if frame_samples > 0:
        g_t = np.concatenate([sample_times(t_start[j], t_end[j], frame_samples) for j in range(k)])
        g_dt_us = np.repeat((t_end - t_start) / frame_samples, frame_samples)
        g_dir, g_int = light.evaluate(g_t)
        shared_light, shared_weight = tensor(g_dir), tensor(g_int * (g_dt_us / US_PER_S * scale)[:, None])
        frame_source.update(shared_t=g_t, shared_dt_us=g_dt_us)
    else:
        # each masked frame pixel takes its super pixel's importance samples of each frame's window
        s_pos, s_frame, s_t, s_dt = _pixel_samples(pre, pixels)
        s_dir, s_int = light.evaluate(s_t)
        s_weight = s_int * (s_dt * scale)[:, None]
        frame_source.update(sample_pixel=s_pos, sample_t=s_t, sample_dt_s=s_dt, sample_weight=s_weight)

    e_t = np.stack([sample_times(t_start[j], t_end[j], ENERGY_SAMPLES) for j in range(k)])
    energy = light.evaluate(e_t.ravel())[1].reshape(k, ENERGY_SAMPLES, 3).mean(axis=1) * ((t_end - t_start) / US_PER_S * scale)[:, None]
    measured = np.asarray(pre.frames, dtype=np.float32).reshape(k, h * w, -1)[:, pixels].reshape(k * p, -1)
    saturated = np.asarray(pre.saturated, dtype=bool).reshape(k, h * w)[:, pixels].reshape(k * p)
    frames = FrameTerms(
        count=k, exposure_s=exposure_s, shared_light=shared_light, shared_weight=shared_weight, shared_visible=None,
        sample_pixel=tensor(s_pos, torch.int64), sample_group=tensor(s_frame * p + s_pos, torch.int64),
        sample_light=tensor(s_dir), sample_weight=tensor(s_weight),
        measured=tensor(measured), saturated=tensor(saturated, torch.bool), energy=tensor(energy), source=frame_source,
    )

    # Event pairs (eq. 25) with the frame pixels under their super pixel; a super pixel that sees
    # past the frame's edge (a calibrated rig's wider event view, a tile's crop) also saw light the
    # frames do not show, so its pairs are left out.
    fp_frame, fp_share = affine_footprints(pre.event_to_frame, (he, we), (h, w))
    pairs = pre.events
    frame_taps = fp_frame[pairs.pixel]
    taps = position[frame_taps]
    area = np.where(taps >= 0, fp_share[pairs.pixel], 0.0)
    inside = fp_share.sum(axis=1)[pairs.pixel] > 1.0 - INSIDE_TOLERANCE
    usable = inside & (area.sum(axis=1) > 0) & (pairs.weight > 0)
    dir_ev, int_ev = light.evaluate(pairs.t_us)
    dir_ref, int_ref = light.evaluate(pairs.t_ref_us)
    grey_w = np.asarray(GREY_WEIGHTS)
    events = EventTerms(
        taps=tensor(np.maximum(taps, 0), torch.int64), tap_weight_now=tensor(area), tap_weight_ref=tensor(area),
        light_now=tensor(dir_ev), light_ref=tensor(dir_ref), tap_area=tensor(area),
        grey_now=tensor(int_ev * grey_w), grey_ref=tensor(int_ref * grey_w),
        target=tensor(pairs.target), weight=tensor(pairs.weight),
        usable=torch.as_tensor(np.flatnonzero(usable), dtype=torch.int64, device=device),
        source={"frame_taps": frame_taps, "area": area, "t_us": pairs.t_us, "t_ref_us": pairs.t_ref_us, "usable": usable,
                "pixel": np.asarray(pairs.pixel, dtype=np.int64), "weight": np.asarray(pairs.weight, dtype=np.float64),
                "rise": np.asarray(pairs.rise, dtype=np.float64), "fall": np.asarray(pairs.fall, dtype=np.float64)},
    )

    v, u = np.divmod(pixels, w)
    ue, ve = frame_to_event(pre.event_to_frame, u.astype(np.float64), v.astype(np.float64))
    grid_index, grid_weight = bilinear_taps(ue, ve, we, he)
    init_normal, init_albedo = start_values(init.normal, init.albedo, pixels, scale)
    coords = np.stack([2.0 * u / max(w - 1, 1) - 1.0, 1.0 - 2.0 * v / max(h - 1, 1)], axis=1)
    geometry = Geometry(
        height=h, width=w, pixels=pixels, coords=tensor(coords), event_shape=(he, we),
        grid_taps=(tensor(grid_index, torch.int64), tensor(grid_weight)),
        tv_pairs=tensor(tv_pairs(mask), torch.int64), view=tensor(np.asarray(view, dtype=np.float64)),
        init_normal=tensor(init_normal), init_albedo=tensor(init_albedo),
    )

    problem = Problem(
        geometry=geometry, frames=frames, events=events, albedo_scale=scale, shadow_fraction=np.zeros((h, w)),
        diagnostics={"pixels": int(p), "frame_samples": int(s_pos.size) if shared_light is None else int(p * shared_light.shape[0]),
                     "albedo_scale": scale},
    )
    problem.apply_mask(ShadowMask.none(h * w, pre.t0_us, pre.period_us))
    return problem


def start_values(normal: np.ndarray, albedo: np.ndarray, pixels: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """(P, 3) start normals (facing the camera where the closed form has none) and (P, 3) albedo in
    units of ``scale`` at ``pixels``, from the (H, W, 3) maps of an ``init.ClosedFormStart``."""
    n = np.asarray(normal, dtype=np.float64).reshape(-1, 3)[pixels]
    bad = ~np.isfinite(n).all(axis=1) | (np.linalg.norm(n, axis=1) < 0.5)
    n[bad] = (0.0, 0.0, 1.0)
    a = np.asarray(albedo, dtype=np.float64).reshape(-1, 3)[pixels] / scale
    return n, np.where(np.isfinite(a), a, 1.0)


def _pixel_samples(pre: Preprocessed, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The importance samples of each masked frame pixel (its super pixel's, shifted to each frame's
    period), grouped by pixel, then by frame, then by phase: (position, frame, t_us, dt_s). Each frame's
    samples are written straight to their places (no sort of the tens of millions of them)."""
    samples = pre.samples
    order = np.lexsort((samples.phase_us, samples.pixel, samples.window))
    window, owner_of = samples.window[order], samples.pixel[order]
    phase, dt = samples.phase_us[order], samples.dt_s[order]
    n_super = pre.event_height * pre.event_width
    covering = pre.super_pixel[pixels]
    chosen = [np.flatnonzero(window == j) for j in pre.frame_window]
    counts = [np.bincount(owner_of[sel], minlength=n_super) for sel in chosen]
    per_pixel = [count[covering] for count in counts]
    total = np.sum(per_pixel, axis=0, dtype=np.int64)
    # a pixel's samples start after all earlier pixels', each frame's after the earlier frames'
    at = np.cumsum(total) - total
    pos = np.repeat(np.arange(pixels.size, dtype=np.int64), total)
    frame, t, dt_s = np.empty(pos.size, dtype=np.int64), np.empty(pos.size), np.empty(pos.size)
    for k, (sel, count, own) in enumerate(zip(chosen, counts, per_pixel, strict=True)):
        runs = np.cumsum(own) - own
        local = np.arange(int(own.sum())) - np.repeat(runs, own)
        index = sel[np.repeat((np.cumsum(count) - count)[covering], own) + local]
        dest = np.repeat(at, own) + local
        shift = float(pre.t_start_us[k]) - (pre.t0_us + pre.windows_us[pre.frame_window[k], 0])
        frame[dest] = k
        t[dest] = pre.t0_us + phase[index] + shift
        dt_s[dest] = dt[index]
        at += own
    return pos, frame, t, dt_s
