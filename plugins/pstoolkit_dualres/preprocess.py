"""DualResPS preprocessing: everything the neural inverse rendering needs, computed once.

    pre = preprocess(capture, PreprocessOptions(), progress)

Steps (one light period of events, starting at the first exposure):

1. Event interval profile at the super pixels (``profile``, eq. 20).
2. Cast shadows by Algorithm 1 (``shadows``), assigned to frame pixels by *nearest* super pixel: the
   frame pixel takes the intervals of the event pixel whose footprint holds it (the inverse of the
   calibrated event→frame affine, rounded). A super pixel's events describe the area mean of exactly
   those frame pixels, and m_c is binary, so a bilinear mix of four neighbours' masks would blur
   the interval ends by mixing in pixels that never saw this one, and need a vote threshold.
3. Irradiance approximation (``irradiance``, supplement eq. 1): a piecewise-constant scale with at
   most three values per period (at the window bounds, or at the strongest spikes of f as in the
   paper: ``scale_rule``), fitted to the super pixels' frame values.
4. Importance samples of each window (``sampling``, eq. 21, 23) per super pixel, shared by its
   frame pixels.
5. Event samples (eq. 25): every pair of consecutive events of a super pixel over the whole stream,
   less pairs that touch a detected shadow or span more than ``max_pair_share`` of the period, with
   the refractory rule and confidence weight of the options.
6. Closed-form initial normal and albedo with the equivalent lights of eq. 14/16 (``init``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

import psfmt
from pstoolkit.errors import UserError
from pstoolkit.eventmodel import consecutive_pairs, reference_time_us
from pstoolkit.lights import LightModel, build_light_model
from pstoolkit.render import GREY_WEIGHTS
from pstoolkit.solver import Progress, no_progress
from pstoolkit_dualres.eventnormal import event_normals
from pstoolkit_dualres.grid import nearest_super_pixel, to_frames
from pstoolkit_dualres.init import closed_form
from pstoolkit_dualres.irradiance import Irradiance, approximate, refractory_log_alpha
from pstoolkit_dualres.profile import interval_profile
from pstoolkit_dualres.sampling import Samples, importance_samples
from pstoolkit_dualres.shadows import (
    ShadowIntervals,
    ShadowTable,
    find_shadows,
    find_silences,
)

ALPHA_RULES = ("reset", "rate")
SCALE_RULES = ("windows", "spikes")
CONFIDENCE_RULES = ("linear", "none")
# θ is at most this share of the spike cap C/R of a refractory period R, and spikes are not used
# below the floor. Simulated blobs (64 px, Lambertian; cast-shadow precision / recall, init MAE
# with vs. without the mask): R = 0: θ 4000, 0.81 / 0.91, 0.40° vs 1.02°; R = 100 µs: θ 1000,
# 0.79 / 0.90, 0.42°; R = 300 µs: θ 333, 0.61 / 0.75, 0.94°; R = 1 ms: θ 100 flags shading
# everywhere (0.34 / 0.74, 9.1°), so no spikes there.
SPIKE_SHARE = 2.0 / 3.0
SPIKE_FLOOR_PER_S = 300.0
# Tolerance (µs) when checking that the exposure windows tile the light period.
TILE_TOLERANCE_US = 2.0


@dataclass
class PreprocessOptions:
    """Options of the preprocessing, with the defaults used by the ``dualres`` solver.

    Shadows (Algorithm 1; thresholds on f of eq. 20, log units per second):
    ``theta_per_s`` θ, a spike that starts a search (default 4000: one threshold crossed within
    C/θ = 37.5 µs at C = 0.15; the approach to an attached shadow exceeds any θ only in its last 1/θ
    seconds, so a high θ keeps lit time out of the mask); ``theta_min_per_s`` θ_min, the lowest
    decayed threshold for a softened edge (500); ``gamma`` γ, the decay factor (0.7);
    ``max_shadow_share`` D as a share of the light period (0.5); ``use_shadows`` False skips
    detection (the "no m_c" ablation). A refractory period R caps |f| at C/R: θ is lowered to 2/3 of
    the cap, and below 300/s (R above about 330 µs at C = 0.15, e.g. the simulator's default 2 ms)
    an edge fires one event and no spike, so there is no mask unless ``silence_ratio`` > 0
    (default 0): then shadows are silences (``shadows.find_silences``) longer than that many times
    both neighbouring intervals. On simulated blobs (64 px) ratio 3 gives precision 0.82, recall
    0.45 at R = 2 ms and leaves the init unchanged (1.01°); at R = 1 ms it gives 0.64 / 0.64 and
    makes the init worse (2.6° vs 1.0°), hence off by default. After the fit (``fast`` preset,
    GGX blobs at R = 2 ms) silences gain little: 1.334° vs 1.349° without a mask at 64 px, 1.420°
    vs 1.437° at 128 px; where spikes are seen (R = 0) the mask is worth more: 0.77° vs 1.31°.

    Irradiance (supplement eq. 1): ``scale_rule`` where the piecewise-constant scale s (at most
    three values per period for three frames) changes: "spikes", the paper's rule, at the three
    events with the largest |f| ≥ ``spike_threshold``; "windows" (default), at the exposure window
    bounds. Both are fitted to the three frame values. Against the true super-pixel irradiance of a
    simulated 48 px sphere (median relative error over lit samples, one global gain), windows 0.030
    vs spikes 0.054 at R = 0 (Lambertian), 0.090 vs 0.128 at R = 2 ms (GGX): the strongest spikes of
    a smooth scene are ordinary shading, and a jump at a window bound also absorbs the quantisation
    and refractory drift of L that the frames of that window measure.

    Sampling (eq. 23): ``sigma`` σ, the density (40; samples per √(saturation unit)), and
    ``max_step_deg``: no sample interval spans more than this sweep of the light (5°).

    Events: ``alpha_rule`` "reset" pairs each event with the reference time t_prev + R of
    ``pstoolkit.eventmodel`` (exact for the simulator, α = 1), "rate" pairs it with t_prev itself and
    α = exp(log change credited to the refractory period, constant-rate assumption);
    ``confidence`` "linear" weights a pair by min(1, Î / (dark_level·Î₉₉)) with Î at its darker
    end (Î₉₉ the 99th percentile of that over all pairs), "none" weights all 1; ``dark_level``
    (0.05); ``max_pair_share`` drops pairs longer than this share of the period (0.5).

    Init: ``init_iterations`` fixed-point steps of the attached-shadow clamp (10, at least 1),
    ``light_samples`` per window for the equivalent lights (64). ``mask_threshold``: a frame pixel is on the object
    when its brightest frame exceeds this share of saturation (0.02).
    """

    theta_per_s: float = 4000.0
    theta_min_per_s: float = 500.0
    gamma: float = 0.7
    max_shadow_share: float = 0.5
    use_shadows: bool = True
    silence_ratio: float = 0.0
    sigma: float = 40.0
    max_step_deg: float = 5.0
    scale_rule: str = "windows"
    alpha_rule: str = "reset"
    confidence: str = "linear"
    dark_level: float = 0.05
    max_pair_share: float = 0.5
    init_iterations: int = 10
    light_samples: int = 64
    mask_threshold: float = 0.02

    def check(self) -> None:
        """UserError naming the first option out of range."""
        limits = [
            ("theta_per_s", self.theta_per_s > 0, "must be positive"),
            ("theta_min_per_s", 0 < self.theta_min_per_s <= self.theta_per_s, "must be positive and at most theta_per_s"),
            ("gamma", 0 < self.gamma < 1, "must be in (0, 1)"),
            ("max_shadow_share", 0 < self.max_shadow_share < 1, "must be in (0, 1)"),
            ("silence_ratio", self.silence_ratio == 0 or self.silence_ratio > 1, "must be 0 (off) or above 1"),
            ("sigma", self.sigma >= 0, "must be non-negative"),
            ("max_step_deg", 0 < self.max_step_deg <= 120, "must be in (0, 120] degrees"),
            ("scale_rule", self.scale_rule in SCALE_RULES, f"must be one of {', '.join(SCALE_RULES)}"),
            ("alpha_rule", self.alpha_rule in ALPHA_RULES, f"must be one of {', '.join(ALPHA_RULES)}"),
            ("confidence", self.confidence in CONFIDENCE_RULES, f"must be one of {', '.join(CONFIDENCE_RULES)}"),
            ("dark_level", 0 <= self.dark_level < 1, "must be in [0, 1)"),
            ("max_pair_share", 0 < self.max_pair_share <= 1, "must be in (0, 1]"),
            ("init_iterations", 0 <= self.init_iterations <= 100, "must be between 0 and 100"),
            ("light_samples", 8 <= self.light_samples <= 4096, "must be between 8 and 4096"),
            ("mask_threshold", 0 <= self.mask_threshold < 1, "must be in [0, 1)"),
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
    affine from event pixel centres to frame pixel coordinates; ``period_us``; ``t0_us`` (the phase
    origin: the first exposure's start); ``light`` (``pstoolkit.lights.LightModel``);
    ``contrast_pos``/``contrast_neg`` (log units), ``refractory_us``.

    Frames: ``frames`` (K, H, W, 3) float32 in saturation units (1 = clipped), ``saturated``
    (K, H, W) bool (a channel at or above 1), ``t_start_us``/``t_end_us`` (K,) int64; ``frame_window``
    (K,) which of the period's ``windows_us`` (J, 2) phase windows frame k covers.

    ``mask`` (H, W) bool: frame pixels on the object.

    Shadows: ``shadow_pixel`` (S,) event flat index, ``shadow_t0_us``/``shadow_t1_us`` (S,) phases
    (t1 < t0: the shadow wraps past the period's end); ``super_pixel`` (H·W,) the event pixel each
    frame pixel takes its shadows from (nearest); ``in_shadow`` evaluates m_c at frame pixels.

    Frame samples (eq. 21): ``frame_sample_pixel`` (M,) frame flat index, ``frame_sample_frame`` (M,)
    frame index k, ``frame_sample_t_us`` (M,) float64 absolute time, ``frame_sample_dt_s`` (M,)
    seconds, so Σ I(t)·dt over a (pixel, frame) group approximates the frame value when I is in
    saturation units per second; samples inside detected shadows are left out (m_c = 0 there).

    Event samples (eq. 25): ``event_pixel`` (E,) event flat index, ``event_t_ref_us`` (E,) float64
    the time of the reference level, ``event_t_us`` (E,) int64 the event, ``event_polarity`` (E,)
    int8, ``event_alpha`` (E,) and ``event_weight`` (E,): the loss compares
    log((Ĩ(t) + ε)/(Ĩ(t_ref) + ε)) with log(α) + p·C^p (ε = ``pstoolkit.eventmodel.LOG_EPS``);
    ``event_frame_uv`` maps event pixels to frame coordinates for rendering them.

    Init: ``init_normal`` (H, W, 3), ``init_albedo`` (H, W, 3) (saturation units per unit light),
    ``effective_lights`` (H, W) int 0–3; ``diagnostics`` JSON-able counts and seconds.
    """

    height: int
    width: int
    event_height: int
    event_width: int
    event_to_frame: np.ndarray
    period_us: float
    t0_us: float
    light: LightModel
    contrast_pos: float
    contrast_neg: float
    refractory_us: float
    frames: np.ndarray
    saturated: np.ndarray
    t_start_us: np.ndarray
    t_end_us: np.ndarray
    frame_window: np.ndarray
    windows_us: np.ndarray
    mask: np.ndarray
    shadow_pixel: np.ndarray
    shadow_t0_us: np.ndarray
    shadow_t1_us: np.ndarray
    super_pixel: np.ndarray
    frame_sample_pixel: np.ndarray
    frame_sample_frame: np.ndarray
    frame_sample_t_us: np.ndarray
    frame_sample_dt_s: np.ndarray
    event_pixel: np.ndarray
    event_t_ref_us: np.ndarray
    event_t_us: np.ndarray
    event_polarity: np.ndarray
    event_alpha: np.ndarray
    event_weight: np.ndarray
    init_normal: np.ndarray
    init_albedo: np.ndarray
    effective_lights: np.ndarray
    diagnostics: dict[str, Any] = field(default_factory=dict)
    shadow_table: ShadowTable | None = field(default=None, repr=False)

    def in_shadow(self, frame_index: np.ndarray, t_us: np.ndarray) -> np.ndarray:
        """m_c (N,) bool at frame pixels ``frame_index`` (N,) and absolute times ``t_us`` (N,): the
        shadows of each frame pixel's nearest super pixel, repeating every period."""
        frame_index = np.asarray(frame_index, dtype=np.int64)
        if self.shadow_table is None:
            return np.zeros(frame_index.shape, dtype=bool)
        phase = np.asarray(t_us, dtype=np.float64) - self.t0_us
        return self.shadow_table.contains(self.super_pixel[frame_index], phase)

    def event_frame_uv(self, event_index: np.ndarray) -> np.ndarray:
        """(N, 2) frame coordinates (u, v) of the centres of event pixels ``event_index`` (N,)."""
        event_index = np.asarray(event_index, dtype=np.int64)
        uv1 = np.stack([event_index % self.event_width, event_index // self.event_width, np.ones(event_index.shape)], axis=-1)
        return uv1.astype(np.float64) @ self.event_to_frame.T


def spike_threshold(options: PreprocessOptions, contrast: float, refractory_us: float) -> float:
    """θ (log units per second) lowered to ``SPIKE_SHARE`` of the cap C/R a refractory period R
    puts on |f| = C/Δt: what counts as an abrupt change for Algorithm 1 and the scale s."""
    cap = contrast / (refractory_us * 1e-6) if refractory_us > 0 else np.inf
    return float(min(options.theta_per_s, SPIKE_SHARE * cap))


def shadow_detector(options: PreprocessOptions, contrast: float, refractory_us: float) -> tuple[str, float, float]:
    """The shadow detector and its thresholds (θ, θ_min).

    θ is ``spike_threshold`` (and θ_min at most θ). When that falls below ``SPIKE_FLOOR_PER_S``
    ordinary shading events reach it and spikes mean nothing: then "silences" if ``silence_ratio``
    > 0, else "off"."""
    if not options.use_shadows:
        return "off", 0.0, 0.0
    theta = spike_threshold(options, contrast, refractory_us)
    if theta >= SPIKE_FLOOR_PER_S:
        return "spikes", theta, min(options.theta_min_per_s, theta)
    return ("silences" if options.silence_ratio > 0 else "off"), 0.0, 0.0


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


def preprocess(capture: psfmt.Capture, options: PreprocessOptions, progress: Progress = no_progress) -> Preprocessed:
    """Preprocess a hybrid capture (see the module docstring); UserError on unusable input."""
    options.check()
    started = time.perf_counter()
    seconds: dict[str, float] = {}
    where = _where(capture)
    frames_in, events_in, light, c_pos, c_neg, refractory = _inputs(capture)
    period = float(light.period_us)
    height, width = frames_in.height, frames_in.width
    event_height, event_width = events_in.height, events_in.width
    n_events_px = event_height * event_width
    affine = capture.calibration.event_to_frame
    if affine is None:
        affine = psfmt.scale_affine(event_width / width)
    t0, windows, frame_window = _windows(frames_in, period, where)
    frames = frames_in.as_float().astype(np.float32)
    saturated = np.any(frames >= 1.0, axis=-1)
    per_window = np.stack([frames[frame_window == j].mean(axis=0) for j in range(len(windows))])
    grey = per_window @ np.asarray(GREY_WEIGHTS, dtype=np.float32)
    mask = grey.max(axis=0) > options.mask_threshold
    if not mask.any():
        raise UserError(f"dualres: {where}: no frame pixel exceeds mask_threshold = {options.mask_threshold:g} of saturation")
    super_pixel = nearest_super_pixel(np.asarray(affine, dtype=np.float64), height, width, event_height, event_width)
    events = events_in.read()
    progress(0.05, "profile")

    tick = time.perf_counter()
    profile = interval_profile(events, event_width, t0_us=t0, period_us=period, contrast_pos=c_pos, contrast_neg=c_neg)
    detector, theta, theta_min = shadow_detector(options, min(c_pos, c_neg), refractory)
    if detector == "spikes":
        found = find_shadows(
            profile,
            theta=theta,
            theta_min=theta_min,
            gamma=options.gamma,
            max_duration_us=options.max_shadow_share * period,
        )
    elif detector == "silences":
        found = find_silences(
            profile, ratio=options.silence_ratio, refractory_us=refractory, max_duration_us=options.max_shadow_share * period
        )
    else:
        found = ShadowIntervals(np.empty(0, np.int64), np.empty(0), np.empty(0))
    table = ShadowTable.build(found, period) if detector != "off" else None
    seconds["shadows"] = time.perf_counter() - tick
    progress(0.2, "irradiance")

    tick = time.perf_counter()
    frame_values = _super_pixel_values(grey.reshape(len(windows), -1), super_pixel, mask, n_events_px)
    # frame values are in saturation units over windows of seconds: Î in saturation units per second
    irradiance = approximate(
        profile.pixel, profile.t_us, profile.p, profile.first, profile.count,
        n_pixels=n_events_px, period_us=period, contrast_pos=c_pos, contrast_neg=c_neg,
        refractory_us=refractory, bounds_us=np.r_[windows[:, 0], windows[-1, 1]], frame_values=frame_values,
        shadows=table, f=profile.f if options.scale_rule == "spikes" else None,
        threshold_per_s=spike_threshold(options, min(c_pos, c_neg), refractory),
    )
    seconds["irradiance"] = time.perf_counter() - tick
    progress(0.35, "sampling")

    tick = time.perf_counter()
    samples = importance_samples(
        irradiance, profile.pixel, profile.t_us, n_pixels=n_events_px, sigma=options.sigma,
        max_step_us=period * options.max_step_deg / 360.0,
    )
    frame_samples = _frame_samples(samples, super_pixel, mask, frame_window, frames_in.t_start_us, windows, t0, period)
    event_samples = _event_samples(events, event_width, irradiance, table, options, c_pos, c_neg, refractory, t0, period)
    seconds["sampling"] = time.perf_counter() - tick
    progress(0.5, "init")

    tick = time.perf_counter()

    def visibility(t_us: np.ndarray, pixels: np.ndarray) -> np.ndarray:
        if table is None:
            return np.ones((len(t_us), len(pixels)), dtype=bool)
        phase = np.repeat(t_us - t0, len(pixels))
        return ~table.contains(np.tile(super_pixel[pixels], len(t_us)), phase).reshape(len(t_us), len(pixels))

    coarse, coarse_known = event_normals(
        event_samples[0], event_samples[1], event_samples[2], event_samples[3], event_samples[4], event_samples[5],
        light, contrast_pos=c_pos, contrast_neg=c_neg, n_pixels=n_events_px,
    )
    super_normal = to_frames(coarse, coarse_known, np.asarray(affine, dtype=np.float64), height, width, event_height, event_width)[0]
    init = closed_form(
        per_window, windows + t0, mask, light,
        visibility=visibility if options.use_shadows else None,
        iterations=options.init_iterations, n_samples=options.light_samples,
        super_normal=super_normal.reshape(height, width, 3),
    )
    seconds["init"] = time.perf_counter() - tick
    progress(1.0, "done")

    coverage = table.coverage(n_events_px) if table is not None else np.zeros(n_events_px)
    diagnostics: dict[str, Any] = {
        "shadow_detector": detector,
        "shadow_theta_per_s": theta,
        "shadow_intervals": int(len(table) if table is not None else 0),
        "shadow_coverage": float(coverage.mean()),
        "profile_samples": len(profile),
        "frame_samples": len(frame_samples[0]),
        "event_samples": len(event_samples[0]),
        "event_pairs": int(event_samples[-1]),
        "effective_lights": {str(n): int(np.sum(init.effective[mask] == n)) for n in range(4)},
        "init_iterations": int(init.iterations),
        "saturated_share": float(saturated[:, mask].mean()) if mask.any() else 0.0,
        "seconds": {**{k: round(v, 4) for k, v in seconds.items()}, "total": round(time.perf_counter() - started, 4)},
    }
    return Preprocessed(
        height=height, width=width, event_height=event_height, event_width=event_width,
        event_to_frame=np.asarray(affine, dtype=np.float64), period_us=period, t0_us=t0, light=light,
        contrast_pos=c_pos, contrast_neg=c_neg, refractory_us=refractory,
        frames=frames, saturated=saturated, t_start_us=frames_in.t_start_us.copy(), t_end_us=frames_in.t_end_us.copy(),
        frame_window=frame_window, windows_us=windows, mask=mask,
        shadow_pixel=found.pixel.astype(np.int64), shadow_t0_us=found.t0_us, shadow_t1_us=found.t1_us,
        super_pixel=super_pixel,
        frame_sample_pixel=frame_samples[0], frame_sample_frame=frame_samples[1],
        frame_sample_t_us=frame_samples[2], frame_sample_dt_s=frame_samples[3],
        event_pixel=event_samples[0], event_t_ref_us=event_samples[1], event_t_us=event_samples[2],
        event_polarity=event_samples[3], event_alpha=event_samples[4], event_weight=event_samples[5],
        init_normal=init.normal, init_albedo=init.albedo, effective_lights=init.effective,
        diagnostics=diagnostics, shadow_table=table,
    )


def _frame_samples(
    samples: Samples,
    super_pixel: np.ndarray,
    mask: np.ndarray,
    frame_window: np.ndarray,
    t_start_us: np.ndarray,
    windows: np.ndarray,
    t0: float,
    period: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each masked frame pixel takes its super pixel's samples of each frame's window, shifted to
    that frame's period: (pixel, frame, t_us, dt_s) arrays."""
    order = np.lexsort((samples.phase_us, samples.pixel, samples.window))
    window, pixel = samples.window[order], samples.pixel[order]
    phase, dt = samples.phase_us[order], samples.dt_s[order]
    n_super = int(super_pixel.max()) + 1 if super_pixel.size else 0
    frame_pixels = np.flatnonzero(mask.ravel())
    out: list[list[np.ndarray]] = [[], [], [], []]
    for k, j in enumerate(frame_window):
        sel = np.flatnonzero(window == j)
        counts = np.bincount(pixel[sel], minlength=n_super)
        offsets = np.cumsum(counts) - counts
        per_pixel = counts[super_pixel[frame_pixels]]
        owner = np.repeat(frame_pixels, per_pixel)
        local = np.arange(owner.size) - np.repeat(np.cumsum(per_pixel) - per_pixel, per_pixel)
        index = sel[offsets[super_pixel[owner]] + local]
        shift = float(t_start_us[k]) - (t0 + windows[j, 0])
        out[0].append(owner)
        out[1].append(np.full(owner.size, k, dtype=np.int64))
        out[2].append(t0 + phase[index] + shift)
        out[3].append(dt[index])
    return (
        np.concatenate(out[0]).astype(np.int64),
        np.concatenate(out[1]),
        np.concatenate(out[2]).astype(np.float64),
        np.concatenate(out[3]).astype(np.float32),
    )


def _event_samples(
    events: psfmt.EventArray,
    width: int,
    irradiance: Irradiance,
    table: ShadowTable | None,
    options: PreprocessOptions,
    c_pos: float,
    c_neg: float,
    refractory: float,
    t0: float,
    period: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """Pairs of consecutive events (pixel, t_ref, t, p, α, w) and the number of pairs before filtering."""
    pairs = consecutive_pairs(events, width)
    interval = (pairs.t_us - pairs.t_prev_us).astype(np.float64)
    keep = interval <= options.max_pair_share * period
    if table is not None:
        keep &= ~table.contains(pairs.pixel, pairs.t_us - t0) & ~table.contains(pairs.pixel, pairs.t_prev_us - t0)
    pixel, t_prev, t, p = pairs.pixel[keep], pairs.t_prev_us[keep], pairs.t_us[keep], pairs.p[keep]
    interval = interval[keep]
    if options.alpha_rule == "reset":
        t_ref = reference_time_us(t_prev, refractory)
        alpha = np.ones(len(t))
    else:
        t_ref = t_prev.astype(np.float64)
        contrast = np.where(p > 0, c_pos, c_neg)
        alpha = np.exp(refractory_log_alpha(p, contrast, interval, refractory))
    if options.confidence == "linear":
        darker = np.minimum(irradiance.value(pixel, t_ref - t0), irradiance.value(pixel, t.astype(np.float64) - t0))
        bright = float(np.percentile(darker, 99)) if darker.size else 0.0
        level = options.dark_level * bright
        weight = np.clip(darker / level, 0.0, 1.0) if level > 0 else np.ones(len(t))
    else:
        weight = np.ones(len(t))
    return pixel, t_ref, t, p, alpha, weight.astype(np.float32), len(pairs.t_us)
