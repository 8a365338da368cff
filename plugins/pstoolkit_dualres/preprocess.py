"""DualResPS preprocessing: everything the inverse rendering needs from a capture, computed once.

    pre = preprocess(capture, PreprocessOptions(), progress)

Steps (one light period of events from the first exposure's start, ``t0_us``):

1. The frames of each exposure window, the object mask, and the nearest super pixel of each frame
   pixel through the calibrated event→frame affine.
2. The evidence shadow detectors read (``pstoolkit.shadows.ShadowEvidence``): the event interval
   profile (eq. 20) of the period at the super pixels, the window means, the sensor.
3. Irradiance approximation (supplement eq. 1, ``irradiance``): a piecewise-constant scale with at
   most three values per period (at the window bounds, or at the strongest spikes of f as in the
   paper: ``scale_rule``), fitted to the super pixels' frame values; it weighs the event pairs and
   places the importance samples.
4. Importance samples of each window (``sampling``, eq. 21, 23) per super pixel, shared by its frame
   pixels (the ``paper`` preset integrates the frames on them), made when first asked for.
5. Event pairs (eq. 25, ``pairs``): consecutive events of a super pixel related exactly by the
   capture's refractory rule, with a confidence weight.
6. The super pixels' normals from their events alone (the EventPS relation, ``eventnormal``), and the
   closed-form start from the per-pixel equivalent lights (``init``, eq. 14/16), here without a
   cast-shadow mask; ``Preprocessed.closed_form`` solves it again under a mask.
7. Where the super pixels' profiles over the turn are mostly specular (``profile_start``; ``start``
   "auto"), or always (``start`` "profile"), their normals from the profiles replace the closed
   form's (``start_normal``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import torch
from torch import Tensor

import psfmt
from pstoolkit import GREY_WEIGHTS, LightModel, Progress, UserError, build_light_model, no_progress
from pstoolkit._shared import devices
from pstoolkit.events.rule import capture_rule
from pstoolkit.grid import check_footprint_extent, default_affine, nearest_super_pixel, to_frames
from pstoolkit.shadows import ShadowEvidence, ShadowMask, interval_profile
from pstoolkit.shadows.spikes import spike_threshold
from pstoolkit.shadows.table_device import DeviceShadowMask
from pstoolkit_dualres.closed_form import ClosedFormStart, closed_form
from pstoolkit_dualres.irradiance import Irradiance, approximate
from pstoolkit_dualres.pairs import EventSamples, event_samples
from pstoolkit_dualres.profile_start import capture_start
from pstoolkit_dualres.sampling import Samples, importance_samples
from pstoolkit_dualres.super_pixel_normals import event_normals

SCALE_RULES = ("windows", "spikes")
CONFIDENCE_RULES = ("linear", "none")
STARTS = ("auto", "closed", "profile")
# Tolerance (µs) when checking that the exposure windows tile the light period.
TILE_TOLERANCE_US = 2.0
# θ of Algorithm 1 that marks the abrupt changes where the "spikes" scale rule may change s.
SCALE_THETA_PER_S = 4000.0


@dataclass
class PreprocessOptions:
    """Options of the preprocessing, with the defaults of the ``dualres`` solver.

    Irradiance (supplement eq. 1): ``scale_rule`` where the piecewise-constant scale s (at most three
    values per period for three frames) changes: "windows" (default) at the exposure window bounds,
    "spikes" (the paper's rule) at the three events with the largest |f| of eq. 20 above the spike
    threshold. Both are fitted to the three frame values.

    Sampling (eq. 23): ``sigma`` σ, the density (samples per √(saturation unit)), and
    ``max_step_deg``: no sample interval spans more than this sweep of the light.

    Events: ``confidence`` "linear" weighs a pair by min(1, Î / (dark_level·Î₅₀)) with Î at its darker
    end (Î₅₀ the median of that over all pairs, ``pairs``), "none" weighs all 1; ``max_pair_share``
    drops pairs longer than this share of the period.

    Closed-form start: ``init_iterations`` fixed-point steps of the attached-shadow clamp (at least 1),
    ``light_samples`` per window for the equivalent lights. ``mask_threshold``: a frame pixel is on
    the object when its brightest window exceeds this share of saturation (frameps's ``threshold``).
    ``start``: "auto" starts from the super pixels' profile normals where the profiles' specular weight
    (``profile_start.specular_weight``) reaches ``profile_start.PROFILE_START_WEIGHT``, "profile"
    always, "closed" never.
    """

    sigma: float = 40.0
    max_step_deg: float = 5.0
    scale_rule: str = "windows"
    confidence: str = "linear"
    dark_level: float = 0.8
    max_pair_share: float = 0.5
    init_iterations: int = 10
    light_samples: int = 64
    mask_threshold: float = 0.002
    start: str = "auto"

    def check(self) -> None:
        """UserError naming the first option out of range."""
        limits = [
            ("sigma", self.sigma >= 0, "must be non-negative"),
            ("max_step_deg", 0 < self.max_step_deg <= 120, "must be in (0, 120] degrees"),
            ("scale_rule", self.scale_rule in SCALE_RULES, f"must be one of {', '.join(SCALE_RULES)}"),
            ("confidence", self.confidence in CONFIDENCE_RULES, f"must be one of {', '.join(CONFIDENCE_RULES)}"),
            ("dark_level", 0 <= self.dark_level < 1, "must be in [0, 1)"),
            ("max_pair_share", 0 < self.max_pair_share <= 1, "must be in (0, 1]"),
            ("init_iterations", 0 <= self.init_iterations <= 100, "must be between 0 and 100"),
            ("light_samples", 8 <= self.light_samples <= 4096, "must be between 8 and 4096"),
            ("mask_threshold", 0 <= self.mask_threshold < 1, "must be in [0, 1)"),
            ("start", self.start in STARTS, f"must be one of {', '.join(STARTS)}"),
        ]
        for name, ok, message in limits:
            if not ok:
                raise UserError(f"dualres: option {name} = {getattr(self, name)!r} {message}")


@dataclass
class Preprocessed:
    """The preprocessed capture (all numpy). Frame pixels are flat indices v·width + u of the frame
    grid, event pixels v_e·event_width + u_e of the event grid; times are absolute µs unless named
    phase (µs since ``t0_us`` modulo ``period_us``).

    Capture: ``height``, ``width``; ``event_height``, ``event_width``; ``event_to_frame`` (2, 3)
    affine from event pixel centres to frame pixel coordinates; ``super_pixel`` (H·W,) the event
    pixel nearest each frame pixel; ``period_us``; ``t0_us``; ``light``; ``contrast_pos``,
    ``contrast_neg`` (log units), ``refractory_us`` and ``refractory_rule``.

    Frames: ``frames`` (K, H, W, 3) float32 in saturation units (1 = clipped), ``saturated`` (K, H, W)
    bool (a channel at or above 1), ``t_start_us``/``t_end_us`` (K,); ``frame_window`` (K,) which of
    the period's ``windows_us`` (J, 2) phase windows frame k covers; ``per_window`` (J, H, W, 3) the
    mean frame of each window. ``mask`` (H, W) bool: frame pixels on the object.

    ``evidence``: what shadow detectors read. ``irradiance``: Î of the super pixels over the period;
    ``samples`` the importance samples of eq. 21/23 placed on it (phases), made on first use.
    ``events``: the event pairs of eq. 25. ``super_normal`` (H, W, 3): the super pixels' event normals
    interpolated to the frame pixels (0 where unknown). ``start_normal`` (H, W, 3): the profile start's
    normals that replace the closed form's where nonzero, or None (step 7). ``init``: the start without a
    cast-shadow mask. The torch device its stages with a device copy run on is ``evidence.device``.
    """

    height: int
    width: int
    event_height: int
    event_width: int
    event_to_frame: np.ndarray
    super_pixel: np.ndarray
    period_us: float
    t0_us: float
    light: LightModel
    contrast_pos: float
    contrast_neg: float
    refractory_us: float
    refractory_rule: str
    frames: np.ndarray
    saturated: np.ndarray
    t_start_us: np.ndarray
    t_end_us: np.ndarray
    frame_window: np.ndarray
    windows_us: np.ndarray
    per_window: np.ndarray
    mask: np.ndarray
    evidence: ShadowEvidence
    irradiance: Irradiance
    events: EventSamples
    super_normal: np.ndarray
    start_normal: np.ndarray | None
    init: ClosedFormStart
    options: PreprocessOptions
    diagnostics: dict[str, Any] = field(default_factory=dict)
    _samples: Samples | None = field(default=None, repr=False)

    @property
    def samples(self) -> Samples:
        """The importance samples of eq. 21/23 at the super pixels, made the first time they are asked
        for (``diagnostics["importance_samples"]`` counts them then): only a fit on the importance
        samples (``frame_samples`` 0, the ``paper`` preset) needs them, and they take some 32 bytes
        each, 0.64 GB at 512² event pixels."""
        if self._samples is None:
            profile = self.evidence.profile
            self._samples = importance_samples(
                self.irradiance, profile.pixel, profile.t_us, n_pixels=self.event_height * self.event_width,
                sigma=self.options.sigma, max_step_us=self.period_us * self.options.max_step_deg / 360.0,
            )
            self.diagnostics["importance_samples"] = len(self._samples.pixel)
        return self._samples

    def closed_form(self, shadows: ShadowMask | None, only: np.ndarray | None = None) -> ClosedFormStart:
        """The closed-form start with the equivalent lights of eq. 14/16 under the cast-shadow mask
        ``shadows`` (None: none); with ``only`` (H, W) bool, solved at those pixels of the mask alone
        (zero elsewhere), the others standing as in ``init`` — exact where ``only`` holds every pixel
        the mask shadows, which the unmasked start already solved."""
        mask, base = (self.mask, None) if only is None else (self.mask & only, self.init)
        return start(self.per_window, self.windows_us + self.t0_us, mask, self.light, self.super_normal,
                     self.options, shadows, base, self.start_normal, self.evidence.device)


def start(per_window: np.ndarray, windows_us: np.ndarray, mask: np.ndarray, light: LightModel,
          super_normal: np.ndarray, options: PreprocessOptions, shadows: ShadowMask | None,
          base: ClosedFormStart | None = None, start_normal: np.ndarray | None = None, device: str = "cpu"
          ) -> ClosedFormStart:
    """The closed-form start (``closed_form.closed_form``) of the window means under a cast-shadow mask,
    its normals replaced by ``start_normal`` where that is given and nonzero.

    Parameters
    ----------
    per_window
        (J, H, W, 3) mean frame of each distinct window of the period, saturation units.
    windows_us
        (J, 2) the windows [t0, t1], absolute µs.
    mask
        (H, W) bool, the pixels solved.
    light
        The directional, periodic light model.
    super_normal
        (H, W, 3) the super pixels' normals from their events, interpolated to the frame pixels (zero
        where unknown).
    options
        The preprocessing options; ``init_iterations`` and ``light_samples`` apply.
    shadows
        The cast-shadow mask at frame pixels, or None or empty (none).
    base
        The start of the pixels outside ``mask`` (``closed_form.closed_form``), or None.
    start_normal
        (H, W, 3) unit normals of the profile start (zero where unknown), or None.
    device
        The torch device of the fixed-point iteration (``closed_form.closed_form``).

    Returns
    -------
    ClosedFormStart
        Normal, albedo and number of effective lights per pixel.
    """
    visibility = None
    if shadows is not None and len(shadows) and devices.on_host(device):
        def visibility(t_us: np.ndarray, pixels: np.ndarray) -> np.ndarray:
            return ~shadows.contains_grid(pixels, t_us)
    elif shadows is not None and len(shadows):
        # the fixed point runs on the device: the lookups too, their answers left there
        there = DeviceShadowMask(shadows, device)

        def visibility(t_us: np.ndarray, pixels: np.ndarray) -> Tensor:
            return ~there.contains_grid(torch.as_tensor(pixels, dtype=torch.int64, device=there.device),
                                        torch.as_tensor(t_us, dtype=torch.float64, device=there.device))

    closed = closed_form(per_window, windows_us, mask, light, visibility=visibility, iterations=options.init_iterations,
                         n_samples=options.light_samples, super_normal=super_normal, base=base, device=device)
    return _with_start_normal(closed, start_normal, mask)


def _with_start_normal(closed: ClosedFormStart, start_normal: np.ndarray | None, mask: np.ndarray) -> ClosedFormStart:
    """``closed`` with its normals replaced by ``start_normal`` (H, W, 3) where that is nonzero in ``mask``."""
    if start_normal is None:
        return closed
    known = mask[..., None] & np.any(start_normal != 0, axis=-1, keepdims=True)
    return replace(closed, normal=np.where(known, start_normal, closed.normal).astype(closed.normal.dtype))


def _profile_start(irradiance: Irradiance, light: LightModel, view: np.ndarray, mask: np.ndarray,
                   super_pixel: np.ndarray, affine: np.ndarray, t0_us: float, period_us: float,
                   event_shape: tuple[int, int], rule: str, device: str) -> tuple[float | None, np.ndarray | None]:
    """The specular weight of the profiles of the super pixels on the object, and by ``rule``
    (``PreprocessOptions.start``) the profile start's normals at the frame pixels (H, W, 3) or None
    (``profile_start.capture_start``, its fits on the torch ``device``); the weight is None where
    ``rule`` is "closed" or no super pixel sees light."""
    if rule == "closed":
        return None, None
    event_height, event_width = event_shape
    height, width = mask.shape
    n_events_px = event_height * event_width
    on_object = np.unique(super_pixel[mask.ravel()])
    weight, normal = capture_start(irradiance, light, view, t0_us, period_us, on_object, rule, device)
    if normal is None:
        return weight, None
    values = np.zeros((n_events_px, 3))
    values[on_object] = normal
    known = np.zeros(n_events_px, dtype=bool)
    known[on_object] = np.any(normal != 0, axis=1)
    frame_normal = to_frames(values, known, affine, height, width, event_height, event_width)[0]
    length = np.linalg.norm(frame_normal, axis=1, keepdims=True)
    return weight, np.where(length > 0, frame_normal / np.maximum(length, 1e-12), 0.0).reshape(height, width, 3)


def _where(capture: psfmt.Capture) -> str:
    return str(capture.path) if capture.path is not None else "the capture"


def _inputs(capture: psfmt.Capture) -> tuple[psfmt.Frames, psfmt.Events, LightModel, float, float, float]:
    """The capture's frames, events, light model and contrasts/refractory, or a UserError."""
    where = _where(capture)
    frames, events = capture.frames, capture.events
    if frames is None or events is None:
        raise UserError(f"dualres: {where} is a {capture.kind} capture; DualResPS needs frames and events")
    if not frames.has_windows:
        raise UserError(f"dualres: {where}: the frames have no exposure windows (t_start_us, t_end_us)")
    if capture.lights is None:
        raise UserError(f"dualres: {where} has no light model")
    light = build_light_model(capture.lights)
    if light.near or not light.period_us:
        raise UserError(f"dualres: {where}: light model {light.name!r} must be directional and periodic")
    if frames.channels != 3:
        raise UserError(f"dualres: {where}: frames have {frames.channels} channels, expected RGB")
    cal = capture.calibration
    if cal.contrast_pos is None or cal.contrast_neg is None:
        raise UserError(f"dualres: {where} has no contrast thresholds in its calibration")
    return frames, events, light, float(cal.contrast_pos), float(cal.contrast_neg), float(cal.refractory_us or 0.0)


def _windows(frames: psfmt.Frames, period_us: float, where: str) -> tuple[float, np.ndarray, np.ndarray]:
    """Phase origin, the period's distinct phase windows (J, 2) tiling [0, T), and each frame's one."""
    t0 = float(frames.t_start_us.min())
    start = np.mod(frames.t_start_us - t0, period_us)
    length = (frames.t_end_us - frames.t_start_us).astype(np.float64)
    distinct, frame_window = np.unique(np.rint(start), return_inverse=True)
    lengths = np.array([length[frame_window == j].max() for j in range(len(distinct))])
    ends = distinct + lengths
    tiles = (
        abs(distinct[0]) <= TILE_TOLERANCE_US
        and np.all(np.abs(ends[:-1] - distinct[1:]) <= TILE_TOLERANCE_US)
        and abs(ends[-1] - period_us) <= TILE_TOLERANCE_US
    )
    if not tiles:
        raise UserError(f"dualres: {where}: the exposure windows do not tile the light period ({period_us:g} µs)")
    return t0, np.stack([distinct, ends], axis=1), frame_window.astype(np.int64)


def _super_pixel_values(values: np.ndarray, super_pixel: np.ndarray, mask: np.ndarray, n_pixels: int) -> np.ndarray:
    """(n_pixels, J) area mean over each super pixel's frame pixels in ``mask`` of ``values`` (J, H·W)."""
    inside = mask.ravel()
    count = np.bincount(super_pixel[inside], minlength=n_pixels)
    sums = np.stack([np.bincount(super_pixel[inside], weights=v[inside], minlength=n_pixels) for v in values], axis=1)
    return sums / np.maximum(count, 1)[:, None]


def preprocess(capture: psfmt.Capture, options: PreprocessOptions, progress: Progress = no_progress,
               device: str = "cpu") -> Preprocessed:
    """Preprocess a hybrid capture (see the module docstring) on the host, the irradiance scale's fit,
    the closed form's iteration and the profile start's fits on the torch ``device`` (which the evidence
    keeps for the shadow detectors); UserError on unusable input."""
    options.check()
    started = time.perf_counter()
    seconds: dict[str, float] = {}
    where = _where(capture)
    frames_in, events_in, light, c_pos, c_neg, refractory = _inputs(capture)
    rule = capture_rule(capture.calibration, f"dualres: {where}")
    period = float(light.period_us)
    height, width = frames_in.height, frames_in.width
    event_height, event_width = events_in.height, events_in.width
    n_events_px = event_height * event_width
    affine = capture.calibration.event_to_frame
    affine = np.asarray(default_affine(event_width, width) if affine is None else affine, dtype=np.float64)
    check_footprint_extent(affine, f"dualres: {where}: /calibration/event_to_frame")
    t0, windows, frame_window = _windows(frames_in, period, where)
    frames = frames_in.as_float().astype(np.float32)
    saturated = np.any(frames >= 1.0, axis=-1)
    per_window = np.stack([frames[frame_window == j].mean(axis=0) for j in range(len(windows))])
    grey = per_window @ np.asarray(GREY_WEIGHTS, dtype=np.float32)
    mask = grey.max(axis=0) > options.mask_threshold
    if not mask.any():
        raise UserError(f"dualres: {where}: no frame pixel exceeds mask_threshold = {options.mask_threshold:g} of saturation")
    super_pixel = nearest_super_pixel(affine, height, width, event_height, event_width)
    events = events_in.read()
    progress(0.1, "profile")

    tick = time.perf_counter()
    profile = interval_profile(events, event_width, t0_us=t0, period_us=period, contrast_pos=c_pos, contrast_neg=c_neg)
    evidence = ShadowEvidence(
        frame_shape=(height, width), event_shape=(event_height, event_width), super_pixel=super_pixel, mask=mask,
        light=light, t0_us=t0, period_us=period, contrast_pos=c_pos, contrast_neg=c_neg, refractory_us=refractory,
        refractory_rule=rule, profile=profile, frames=per_window, windows_us=windows, device=device,
    )
    frame_values = _super_pixel_values(grey.reshape(len(windows), -1), super_pixel, mask, n_events_px)
    # frame values are in saturation units over windows of seconds: Î in saturation units per second
    irradiance = approximate(
        profile.pixel, profile.t_us, profile.p, profile.first, profile.count,
        n_pixels=n_events_px, period_us=period, contrast_pos=c_pos, contrast_neg=c_neg,
        refractory_us=refractory, bounds_us=np.r_[windows[:, 0], windows[-1, 1]], frame_values=frame_values,
        f=profile.f if options.scale_rule == "spikes" else None,
        threshold_per_s=spike_threshold(SCALE_THETA_PER_S, min(c_pos, c_neg), refractory), device=device,
    )
    seconds["irradiance"] = time.perf_counter() - tick
    progress(0.35, "sampling")

    tick = time.perf_counter()
    pairs = event_samples(events, event_width, irradiance, rule=rule, refractory_us=refractory, contrast_pos=c_pos,
                          contrast_neg=c_neg, t0_us=t0, period_us=period, confidence=options.confidence,
                          dark_level=options.dark_level, max_pair_share=options.max_pair_share)
    seconds["sampling"] = time.perf_counter() - tick
    progress(0.5, "init")

    tick = time.perf_counter()
    coarse, coarse_known = event_normals(pairs.pixel, pairs.t_ref_us, pairs.t_us, pairs.target, pairs.weight, light,
                                         n_pixels=n_events_px)
    super_normal = to_frames(coarse, coarse_known, affine, height, width, event_height, event_width)[0].reshape(height, width, 3)
    closed = start(per_window, windows + t0, mask, light, super_normal, options, None, device=device)
    weight, start_normal = _profile_start(irradiance, light, capture.calibration.view_direction, mask, super_pixel,
                                          affine, t0, period, (event_height, event_width), options.start, device)
    init = _with_start_normal(closed, start_normal, mask)
    seconds["init"] = time.perf_counter() - tick
    progress(1.0, "done")
    diagnostics = {
        "refractory_rule": rule,
        "profile_samples": len(profile),
        "event_pairs": len(pairs.pixel),
        "effective_lights": {str(n): int(np.sum(init.effective[mask] == n)) for n in range(4)},
        "init_iterations": int(init.iterations),
        "specular_weight": weight,
        "start": "closed" if start_normal is None else "profile",
        "saturated_share": float(saturated[:, mask].mean()),
        "seconds": {**{k: round(v, 4) for k, v in seconds.items()}, "total": round(time.perf_counter() - started, 4)},
    }
    return Preprocessed(
        height=height, width=width, event_height=event_height, event_width=event_width, event_to_frame=affine,
        super_pixel=super_pixel, period_us=period, t0_us=t0, light=light, contrast_pos=c_pos, contrast_neg=c_neg,
        refractory_us=refractory, refractory_rule=rule, frames=frames, saturated=saturated,
        t_start_us=frames_in.t_start_us.copy(), t_end_us=frames_in.t_end_us.copy(), frame_window=frame_window,
        windows_us=windows, per_window=per_window, mask=mask, evidence=evidence, irradiance=irradiance, events=pairs,
        super_normal=super_normal, start_normal=start_normal, init=init, options=options, diagnostics=diagnostics,
    )
