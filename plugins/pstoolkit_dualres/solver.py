"""The ``dualres`` solver: DualResPS (three long exposures + events) by inverse rendering.

Pipeline: ``preprocess`` → the shadow detector of the registry (``--set shadow_detector=NAME``; one
that uses the surface, ``geometry`` or ``fused``, on the closed-form start's normals) → the closed form
again under its mask → ``problem.build_problem`` with the mask → Adam on the frame, event and TV losses
(eq. 24–26, ``train``) in stages: a detector that uses the surface runs again on the
fitted normals between stages (``presets.Preset.detect_at``) and its mask is applied to the frames and
events, the fit carrying on from where it is (restarting the pixels it shadows from the closed form
under it cost path-traced concavities 0.1–0.3°: under inter-reflection the closed form is the worse
start, ``benchmarks/NOTES.md``); with ``event_gate`` κ the event pixels whose pairs the fit cannot
explain weigh less from then on and their frame pixels restart from the closed form (``consistency``).
From the first re-detection on, the light one diffuse bounce of inter-reflection adds
(``interreflection``, reflectance ``bounce_reflectance``) is predicted from the fitted surface and taken
out of the frames and events; with ``interreflection=auto`` (the default) the fit goes on both with the
bounce and without, and keeps the bounce unless that fit leaves more than ``BOUNCE_TOLERANCE`` more of
the measurements unexplained (``interreflection.unexplained``): a renderer without inter-reflection, or
a surface whose bounce the model predicts wrongly, contradicts it there.
The reflectance model is a BRDF of the registry (``--set brdf=NAME``, ``reflectance.FitModel``), with
``indirect`` an indirect-light map beside it.

Outputs: ``normal``; the BRDF's maps (``albedo``, ``f0``, ``roughness`` for ``ggx``; radiometric ones
in frame units per unit light per second, the exposure gain folded in), the maps they imply in other
workflows (``metallic`` and ``base_color`` for ``ggx``, computed on albedo and F0 relative to the
capture's albedo scale), ``cast_shadow`` (the share of each pixel's exposure time the final mask
removed) and ``unlit`` (1 where the normal continues the fitted surface over pixels no light reached,
``unlit``).
"""

from __future__ import annotations

import copy
import time
from collections.abc import Callable, Generator, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import nn

import psfmt
from pstoolkit import BRDF, Option, Progress, ShadowDetector, ShadowMask, Solver, SolverResult, UserError, get_registries
from pstoolkit.plugin.options import format_assignments
from pstoolkit.shadows.surface_sweep import integrated_height
from pstoolkit.solve.tiled import solve_tiles
from pstoolkit_dualres.consistency import event_gate
from pstoolkit_dualres.fields import NeuralField, PyramidField
from pstoolkit_dualres.interreflection import remove_bounce, unexplained
from pstoolkit_dualres.preprocess import SCALE_RULES, STARTS, Preprocessed, PreprocessOptions, preprocess
from pstoolkit_dualres.presets import OVERRIDES, PRESETS, Preset, resolve
from pstoolkit_dualres.problem import Problem, build_problem, start_values
from pstoolkit_dualres.reflectance import FitModel, reflects_indirect
from pstoolkit_dualres.thresholds import REFIT_EVERY, THRESHOLD_FITS, ThresholdGains, fit_thresholds
from pstoolkit_dualres.tiling import plan
from pstoolkit_dualres.train import StageConfig, Training
from pstoolkit_dualres.unlit import fill_unlit, unlit_pixels

# The event gate's bound is at least this share of the smaller contrast threshold: the residual an
# event's own quantisation leaves (consistency.event_gate).
GATE_FLOOR = 0.5
# Share of the progress bar given to preprocessing.
PREPROCESS_SHARE = 0.1
# The choices of ``interreflection``, and the default γ of its bounce: about a bright plastic's or paint's
# diffuse reflectance.
BOUNCE_MODES = ("auto", "on", "off")
BOUNCE_REFLECTANCE = 0.6
# ``interreflection=auto`` keeps the bounce when the fit with it leaves at most this share more of the
# frames and events as measured unexplained (``interreflection.unexplained``) than the fit without.
BOUNCE_TOLERANCE = 0.1
# ``interreflection=auto`` (with ``bounce_early``) compares its two fits at these shares of the epochs after
# the first re-detection too, and goes on with one alone where the ratio of what they leave unexplained is
# further than the margin from 1 + BOUNCE_TOLERANCE; else at the end. The margins hold every choice of the
# realism grid's 48 captures the bounce is tried on to the one at the end: from a third of the epochs on,
# the ratio rose by up to 0.11 (path-traced `relief`, whose bounce is wrong) and fell by up to 0.05; from
# two thirds on, it moved by 0.03 at most (``benchmarks/NOTES.md``).
BOUNCE_CHECKS = ((1 / 3, 0.12), (2 / 3, 0.03))
# A bounce below this share of the measured frames is not worth a second fit (a convex object, a metal).
MIN_BOUNCE_SHARE = 0.002


# A fit's records (one per stage after its first) and the history of its training.
Fitted = tuple[list[dict[str, Any]], list[dict[str, float]]]
# What a paused fit is sent to go on: the progress bar's place of its next epochs, whether to pause again
# (None starts a new one).
GoOn = tuple[Callable[[float], float], bool] | None


def _to_end(fit: Generator[None, GoOn, Fitted], place: Callable[[float], float] | None = None) -> Fitted:
    """``fit`` (a ``DualRes.solve_whole`` fitting, new or paused) run to its end without a pause, its
    progress bar at ``place`` from where it paused; what it returns."""
    try:
        fit.send(None if place is None else (place, False))
    except StopIteration as end:
        return end.value
    raise RuntimeError("a fit told to go on to its end paused")


@dataclass
class FitState:
    """A fit at one point, to come back to: copies of the field's and the model's parameters, the
    problem's terms (their tensors are replaced, never changed in place, by every ``apply_``), the mask
    and the threshold fits."""

    parameters: tuple[dict[str, Any], list[torch.Tensor]]
    terms: tuple[dict[str, Any], dict[str, Any], dict[str, Any]]
    shadows: ShadowMask
    gains: list[ThresholdGains]

    @classmethod
    def take(cls, problem: Problem, field: nn.Module, model: FitModel, shadows: ShadowMask, gains: list[ThresholdGains]) -> FitState:
        return cls(parameters=(copy.deepcopy(field.state_dict()), [p.detach().clone() for p in model.parameters()]),
                   terms=({**vars(problem.frames), "source": dict(problem.frames.source)},
                          {**vars(problem.events), "source": dict(problem.events.source)},
                          {"shadow_fraction": problem.shadow_fraction, "diagnostics": dict(problem.diagnostics)}),
                   shadows=shadows, gains=list(gains))

    def restore(self, problem: Problem, field: nn.Module, model: FitModel, gains: list[ThresholdGains]) -> None:
        """Put the fit back as it was taken (``gains`` is refilled in place)."""
        field.load_state_dict(self.parameters[0])
        with torch.no_grad():
            for parameter, value in zip(model.parameters(), self.parameters[1]):
                parameter.copy_(value)
        frames, events, rest = self.terms
        vars(problem.frames).update({**frames, "source": dict(frames["source"])})
        vars(problem.events).update({**events, "source": dict(events["source"])})
        problem.shadow_fraction = rest["shadow_fraction"]
        problem.diagnostics = dict(rest["diagnostics"])
        gains[:] = self.gains


@contextmanager
def deterministic(device: torch.device) -> Iterator[None]:
    """Torch's deterministic kernels for the duration on the CPU (the scatter-adds of gathers' gradients
    are not, by default, on several threads), so a CPU run repeats bit for bit. Not on CUDA: there they
    would replace the bilinear upsampling of the pyramid's levels by a Python decomposition whose
    backward is a sorted ``index_put`` (20 ms a step at 256² on an H200, most of the training time), and
    the scatter-adds by sorts; a CUDA run repeats to float rounding."""
    if device.type != "cpu":
        yield
        return
    enabled, warn = torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled()
    torch.use_deterministic_algorithms(True)
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(enabled, warn_only=warn)


class Stopwatch:
    """Wall seconds of a run's stages, for its diagnostics: ``lap(name)`` books the time since the
    previous lap (or the start) under ``name``, adding up when a name repeats."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self._last = time.perf_counter()

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.seconds[name] = self.seconds.get(name, 0.0) + now - self._last
        self._last = now

    def record(self) -> dict[str, float]:
        """The stages in the order first booked, rounded to 0.1 ms, with their ``total``."""
        return {**{k: round(v, 4) for k, v in self.seconds.items()}, "total": round(sum(self.seconds.values()), 4)}


def build_field(preset: Preset, problem: Problem, model: FitModel) -> nn.Module:
    """``pyramid`` → PyramidField from the closed-form start; ``mlp`` → the paper's NeuralField, its
    albedo everywhere the closed form's median (per channel)."""
    geometry = problem.geometry
    smooth_init = model.raw_init("smooth").to(problem.device, problem.dtype)
    if preset.field == "mlp":
        # albedo is in units of the capture's bright albedo: a textured object's typical pixel is darker, and
        # a network started at the bright one turns its normals away from the light faster than its albedo
        # comes down (path-traced textured `relief`: the normals sideways within 15 epochs)
        typical = torch.nanmedian(geometry.init_albedo, dim=0).values[None]
        return NeuralField(geometry.coords, model.pixel_raw_from(typical)[0], smooth_init).to(problem.device)
    return PyramidField(
        (geometry.height, geometry.width), geometry.pixels, geometry.init_normal, model.pixel_raw_from(geometry.init_albedo),
        geometry.event_shape, geometry.grid_taps, smooth_init, smoothness=preset.smoothness,
    )


def threshold_sigma(capture: psfmt.Capture, option: float) -> float:
    """The spread of the event pixels' thresholds the fit assumes (log units): ``option``, or where it
    is 0 the capture's sensor record's ``contrast_sigma`` (0 when it records none)."""
    if option > 0:
        return option
    record = capture.calibration.sensor_model or {}
    recorded = record.get("contrast_sigma")
    return float(recorded) if recorded is not None and np.isfinite(recorded) and recorded > 0 else 0.0


def _current(field: nn.Module, model: FitModel) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """The fit's (P, 3) normals and its BRDF's maps now, without gradients."""
    with torch.no_grad():
        normal, pixel_raw, smooth_raw = field()
        return normal, model.maps(pixel_raw, smooth_raw)


def _frame_normal(problem: Problem, normal: torch.Tensor) -> np.ndarray:
    """(H, W, 3) float32 frame map of the fit's (P, 3) ``normal``, zero off the masked pixels."""
    h, w, pixels = problem.geometry.height, problem.geometry.width, problem.geometry.pixels
    full = np.zeros((h * w, 3), dtype=np.float32)
    full[pixels] = normal.detach().cpu().numpy()
    return full.reshape(h, w, 3)


def _stage_bounds(preset: Preset, detector: ShadowDetector, between: bool) -> list[int]:
    """Epochs at which the stages start, then the last epoch: at the preset's ``detect_at`` when the
    detector uses the surface or something else runs ``between`` stages (the event gate of
    ``consistency``, the bounce of ``interreflection``), else one stage."""
    cuts = sorted({int(round(share * preset.epochs)) for share in preset.detect_at}) if detector.uses_surface or between else []
    return [0, *[c for c in cuts if 0 < c < preset.epochs], preset.epochs]


class DualRes(Solver):
    name = "dualres"
    summary = "DualResPS: three long-exposure frames + events, inverse rendering with cast shadows (torch)"
    options = (
        Option("preset", str, "fast", "fast (multi-resolution per-pixel field, closed-form start) or paper (the paper's MLP, 1200 epochs)",
               choices=tuple(PRESETS)),
        Option("epochs", int, -1, "Adam epochs; 0 returns the closed-form start (−1 = the preset's: fast 150, paper 1200)", minimum=-1),
        Option("seed", int, 0, "seed of the network initialisation and the event batches"),
        Option("brdf", str, "ggx", "reflectance model, a registered BRDF (ggx, lambertian, sg, mlp-bases, metallic, or a plugin's)"),
        Option("shadow_detector", str, "fused", "cast-shadow detector, a registered one (fused, geometry, silences, spikes, none, or a plugin's)"),
        Option("shadow", str, (), "an option of the shadow detector (its options are listed under shadow detectors)",
               multiple=True, nested=True),
        Option("lr", float, -1.0, "learning rate of the surface (−1 = the preset's: fast 5e-3, paper 1e-3)", minimum=-1.0),
        Option("material_lr", float, -1.0, "learning rate of the smooth materials (−1 = the preset's)", minimum=-1.0),
        Option("frame_weight", float, 1.0, "λ_f, weight of the frame loss (eq. 24)", minimum=0.0),
        Option("event_weight", float, -1.0, "λ_e, weight of the event loss (eq. 25) (−1 = the preset's: 8)", minimum=-1.0),
        Option("event_huber", float, 0.1,
               "Huber δ of the event residual, log units: residuals beyond it pull linearly (0 = the paper's square)",
               minimum=0.0),
        Option("event_gate", float, 0.0,
               "κ of the event pixels' consistency gate between stages: a pixel whose events the fit leaves with a residual "
               "scale above κ times the typical one (and above half the contrast threshold) weighs (bound/scale)², its frame "
               "pixels restart from the closed form below one half (0 = off)", minimum=0.0),
        Option("thresholds", str, "balance",
               "what the fit estimates of each event pixel's contrast thresholds every 10 epochs, with the prior of "
               "threshold_sigma: balance (the ratio of its C⁺ to its C⁻, which shading cannot imitate: rises and falls "
               "pass the same levels over a turn), both (also their common scale, relative to its 3×3 neighbours': "
               "light a concavity reflects into itself imitates part of that), or nominal (neither)", choices=THRESHOLD_FITS),
        Option("threshold_sigma", float, 0.0,
               "spread σ of the event pixels' thresholds around the nominal C⁺ and C⁻, log units, the prior of "
               "`thresholds` (0 = the capture's sensor record; the nominal thresholds where it records none)",
               minimum=0.0, maximum=1.0),
        Option("indirect", bool, True,
               "fit an indirect-light map b (smooth, ≥ 0): light from other parts of the object that the diffuse albedo "
               "reflects and no cast shadow removes (inter-reflection in concavities, a room's ambient light); with a BRDF "
               "that has an RGB diffuse albedo"),
        Option("interreflection", str, "auto",
               "one diffuse bounce of inter-reflection, predicted from the fitted surface and taken out of the frames and "
               "events at each re-detection: auto (from the first re-detection on the fit goes on with it and without, and "
               f"keeps it unless it leaves more than {100 * BOUNCE_TOLERANCE:g} % more of the measurements unexplained), on "
               "or off", choices=BOUNCE_MODES),
        Option("bounce_early", bool, True,
               "interreflection=auto: compare the fits with and without the bounce at a third and at two thirds of the "
               "epochs after the first re-detection too, and go on with one alone once the comparison is clear (the "
               "ratio of what they leave unexplained 0.12, then 0.03, from the tolerance); false: both fit to the end"),
        Option("bounce_reflectance", float, BOUNCE_REFLECTANCE,
               "γ of interreflection: the reflectance of the capture's bright albedo (the fitted albedo is relative to it; "
               "about a bright plastic's or paint's diffuse reflectance)", minimum=0.01, maximum=2.0),
        Option("indirect_sparsity", float, 0.05, "weight of the L1 penalty that keeps b at 0 where the direct light "
               "explains the frames", minimum=0.0),
        Option("tv_weight", float, -1.0, "λ_tv, weight of the TV warm-up (−1 = the preset's)", minimum=-1.0),
        Option("tv_fraction", float, -1.0, "share of each stage's epochs over which the TV term fades to zero (−1 = the preset's)",
               minimum=-1.0, maximum=1.0),
        Option("smoothness", float, -1.0, "fast: weight of the penalty on the pyramid's finer levels (−1 = the preset's)", minimum=-1.0),
        Option("event_batch", int, 131072, "event pairs drawn per full-batch step (0 = all)", minimum=0),
        Option("frame_samples", int, -1,
               "samples per frame on a time grid shared by all pixels; 0 = the per-pixel importance samples of "
               "preprocessing (−1 = the preset's: fast 8, paper 0)", minimum=-1),
        Option("batch_pixels", int, -1,
               "frame pixels per mini-batch, an epoch being a pass over all pixels; 0 = one full-batch step per "
               "epoch (−1 = the preset's: fast 0, paper 512)", minimum=-1),
        Option("compile", bool, False,
               "run the mini-batch steps (batch_pixels > 0, the paper preset) through torch.compile: fused kernels, "
               "after a compile of some tens of seconds on first use (cached on disk); on a GPU the compiled steps are "
               "replayed as CUDA graphs like the plain ones"),
        Option("scale_rule", str, "windows",
               "where the irradiance scale s may change: windows (exposure-window bounds) or spikes (the strongest "
               "event bursts, at most three values per turn, as in the paper)", choices=SCALE_RULES),
        Option("fill_unlit", bool, True,
               "give the pixels dark in every exposure that the lit object encloses (a pit's bottom in cast shadow "
               "all turn) the harmonic continuation of the fitted surface's slopes around them, marked in the unlit "
               "map; false leaves them out"),
        Option("start", str, "auto",
               "where the fit starts: closed (the closed form from the exposures, Lambertian), profile (each super "
               "pixel's normal whose diffuse + GGX profile over the turn fits its events best), or auto (profile where "
               "the profiles say the GGX lobe carries at least 75 % of the light, as on metals; otherwise closed)", choices=STARTS),
        Option("memory_gb", float, 0.0,
               "memory the run may use, GB: the capture is solved in tiles when it needs more (on this machine: this "
               "process and its local cluster together; with --scheduler, per worker); 0 = half the machine's",
               minimum=0.0),
        Option("tile_px", int, 0,
               "frame pixels per side of a tile's core; 0 = as memory_gb allows (one tile when the capture fits), "
               "-1 = never tile", minimum=-1),
        Option("overlap_px", int, 64, "frame pixels each tile reaches into its neighbours; the seams are blended over this width",
               minimum=0),
    )
    needs = frozenset({"frames", "events", "lights"})
    tiled = True
    shadows: ShadowMask | None = None
    """The cast-shadow mask the last ``solve`` ended with (for inspection from Python)."""

    @classmethod
    def resolve_options(cls, options: dict[str, Any]) -> dict[str, Any]:
        """The options with the preset expanded: every override left at −1 ("the preset's") becomes
        the preset's value, and ``shadow`` lists every option of the shadow detector (``key=value``
        strings, defaults filled in), so result.json records what the run used. Idempotent: the
        preset stays named and the expanded values are the ones it would give. UserError for
        ``smoothness`` with a preset whose field is the MLP, which has no pyramid to smooth (its own
        value, 0, is accepted: it is what the run uses); ``compile`` with full-batch steps, which it does
        not compile; an unknown shadow detector or detector option."""
        named = PRESETS[options["preset"]]
        if named.field == "mlp" and options["smoothness"] >= 0 and options["smoothness"] != named.smoothness:
            raise UserError(
                f"dualres: option smoothness={options['smoothness']:g} cannot apply with preset={named.name}: "
                "it weighs the pyramid's finer levels, and this preset's field is an MLP (no pyramid)"
            )
        if options["interreflection"] == "off" and options["bounce_reflectance"] != BOUNCE_REFLECTANCE:
            raise UserError(f"dualres: option bounce_reflectance={options['bounce_reflectance']:g} cannot apply with "
                            "interreflection=off: it is the reflectance of the bounce that option takes out")
        if options["interreflection"] != "auto" and not options["bounce_early"]:
            raise UserError(f"dualres: option bounce_early=false cannot apply with interreflection={options['interreflection']}: "
                            "it is when auto compares its fits with and without the bounce")
        preset = resolve(options)
        if options["compile"] and preset.batch_pixels == 0:
            raise UserError("dualres: option compile=true cannot apply with full-batch steps (batch_pixels=0, as in "
                            f"preset={preset.name}): it compiles the mini-batch steps; set batch_pixels or preset=paper")
        detector = get_registries().shadow_detectors.get(options["shadow_detector"])
        shadow = format_assignments(detector.parse_options(options["shadow"]), detector.options)
        return {**options, **{name: getattr(preset, name) for name in OVERRIDES}, "shadow": tuple(shadow)}

    def solve(self, capture: psfmt.Capture, options: dict[str, Any], progress: Progress) -> SolverResult:
        """The whole capture in one piece, or in tiles (``tiling.plan``) on Dask when it needs more
        memory than ``memory_gb``, ``tile_px`` asks for tiles, or a scheduler is given."""
        tiles = plan(psfmt.target_size(capture), options, scheduler=self.scheduler, workers=self.workers)
        if tiles is None:
            return self.solve_whole(capture, options, progress)
        return solve_tiles(capture, tiles, solver=self.name, device=str(self.device), options={**options, "tile_px": -1},
                           overlap_px=options["overlap_px"], scheduler=self.scheduler, workers=self.workers, progress=progress)

    def solve_whole(self, capture: psfmt.Capture, options: dict[str, Any], progress: Progress) -> SolverResult:
        """DualResPS on the whole capture at once (the module docstring's pipeline)."""
        torch.manual_seed(options["seed"])
        preset = resolve(options)
        registries = get_registries()
        detector_entry = registries.shadow_detectors.get(options["shadow_detector"])
        detector_options = detector_entry.parse_options(options["shadow"])
        detector: ShadowDetector = detector_entry.obj()
        brdf: BRDF = registries.brdfs.get(options["brdf"]).obj()
        if not getattr(brdf, "fit", ()):
            raise UserError(f"dualres: BRDF {options['brdf']!r} declares no fit parameters (BRDF.fit) to estimate")
        # a BRDF without a diffuse albedo (sg, mlp-bases, metallic …) has nothing to reflect it with
        model = FitModel(brdf, indirect=options["indirect"] and reflects_indirect(brdf)).to(self.device)
        started = time.perf_counter()
        clock = Stopwatch()
        progress(0.0, "preprocessing")
        pre = preprocess(capture, PreprocessOptions(scale_rule=options["scale_rule"], start=options["start"]),
                         lambda fraction, message: progress(PREPROCESS_SHARE * fraction, message), device=str(self.device))
        clock.lap("preprocess")
        # a detector that uses the surface starts from the closed form's: the fit's first stage then
        # already leaves out the shadows it predicts (the events confirm them, with ``fused``)
        evidence = pre.evidence.with_normal(pre.init.normal) if detector.uses_surface else pre.evidence
        shadows = detector.detect(evidence, detector_options)
        clock.lap("detect")
        init = pre.closed_form(shadows) if len(shadows) else pre.init
        clock.lap("closed_form")
        problem = build_problem(pre, capture.calibration.view_direction, device=self.device, frame_samples=preset.frame_samples,
                                init=init)
        problem.apply_mask(shadows)
        clock.lap("problem")
        seconds_pre = time.perf_counter() - started
        gated = options["event_gate"] > 0
        mode, gamma = options["interreflection"], options["bounce_reflectance"]
        if mode == "on" and model.diffuse is None:
            raise UserError(f"dualres: BRDF {options['brdf']!r} has no RGB diffuse albedo to reflect inter-reflected light "
                            "(interreflection=on)")
        bouncing = mode != "off" and model.diffuse is not None
        bounds = _stage_bounds(preset, detector, gated or bouncing)
        spans = list(zip(bounds[:-1], bounds[1:]))
        stages: list[dict[str, Any]] = [{"epoch": 0, "shadow_intervals": len(shadows), "cast_shadow_share": problem.diagnostics["cast_shadow_share"],
                                         **shadows.diagnostics}]
        history: list[dict[str, float]] = []
        sigma = threshold_sigma(capture, options["threshold_sigma"]) if options["thresholds"] != "nominal" else 0.0
        gains: list[ThresholdGains] = []

        comparing = bouncing and mode == "auto" and len(spans) > 1
        rest_from, last_epoch = spans[1][0] if len(spans) > 1 else 0, spans[-1][1]
        # the epochs interreflection=auto compares its two fits at, each with its margin, the last epoch last
        checks = sorted({min(rest_from + max(1, int(round(share * (last_epoch - rest_from)))), last_epoch): margin
                         for share, margin in (BOUNCE_CHECKS if options["bounce_early"] else ())}.items())
        checks = [(epoch, margin) for epoch, margin in checks if epoch < last_epoch] + [(last_epoch, 0.0)]
        # the progress bar counts the epochs of both fits after the first re-detection, as if neither stopped early
        total = max(last_epoch + (last_epoch - rest_from if comparing else 0), 1)

        def place_of(epoch: float) -> float:
            """The share of the run's training done at ``epoch`` of a fit that trains on alone."""
            return epoch / total

        def refit(epoch: int) -> None:
            if epoch > 0 and epoch % REFIT_EVERY == 0:
                gains.append(fit_thresholds(problem, field, model, (pre.event_height, pre.event_width), sigma, pre.contrast_pos,
                                            pre.contrast_neg, common=options["thresholds"] == "both"))
                problem.events.apply_thresholds(gains[-1].gain_pos, gains[-1].gain_neg)

        def between(stage: int, reflectance: float) -> dict[str, Any]:
            """What runs before ``stage`` > 0: the detector again, the gate, the bounce of ``reflectance``."""
            nonlocal shadows
            record: dict[str, Any] = {"epoch": spans[stage][0]}
            if detector.uses_surface:
                shadows = self._detect_again(detector, detector_options, pre, problem, field, reflectance > 0)
                clock.lap(f"redetect_{stage}")
                record.update(shadow_intervals=len(shadows), cast_shadow_share=problem.diagnostics["cast_shadow_share"],
                              **shadows.diagnostics)
            if gated:
                gate = event_gate(problem, field, model, pre.event_height * pre.event_width, options["event_gate"],
                                  GATE_FLOOR * min(pre.contrast_pos, pre.contrast_neg))
                problem.events.apply_gate(gate.weight)
                self._restart(pre, problem, field, model, shadows, self._gated_pixels(problem, gate.restart))
                clock.lap(f"gate_{stage}")
                record.update(gate.record())
            if reflectance > 0:
                record.update(self._bounce(pre, problem, field, model, shadows, reflectance))
                clock.lap(f"bounce_{stage}")
            return record

        def fitting(stage: int, reflectance: float, place: Callable[[float], float], pauses: tuple[int, ...] = (),
                    until: int | None = None) -> Generator[None, GoOn, Fitted]:
            """Train ``stage`` and the ones after it up to ``until`` (default: all; ``between`` each but the
            first, at ``reflectance``), ``place(epoch)`` the share of the run's training done at an epoch for
            the progress bar; their records and history. At each of ``pauses`` (epochs after ``stage``'s
            first, ascending) it stops, before anything that runs between stages, and goes on when sent the
            ``place`` of its next epochs and whether to stop at the pauses left."""
            records: list[dict[str, Any]] = []
            fitted: list[dict[str, float]] = []
            places = [place]
            pausing = True
            for index in range(stage, len(spans) if until is None else until):
                first, last = spans[index]
                if index > stage:
                    records.append(between(index, reflectance))
                config = self._stage(preset, options, last - first, options["seed"] + index)

                def report(fraction: float, message: str, first: int = first, last: int = last) -> None:
                    progress(PREPROCESS_SHARE + (1.0 - PREPROCESS_SHARE) * places[-1](first + fraction * (last - first)), message)

                # no detection of this stage's surface is left to come
                pre.evidence.forget()
                training = Training(problem, field, model, config, report,
                                    before_epoch=(lambda epoch, first=first: refit(first + epoch)) if sigma > 0 else None)
                try:
                    for pause in pauses:
                        if pausing and first < pause <= last:
                            training.run(pause - first)
                            clock.lap(f"train_{index}")
                            sent, pausing = yield
                            places.append(sent)
                    training.run()
                finally:
                    training.close()
                fitted += training.history
                clock.lap(f"train_{index}")
            return records, fitted

        def segment(lo: int, hi: int, done: float, to: float) -> Callable[[float], float]:
            """The progress bar's ``place`` that takes the epochs ``lo``..``hi`` from ``done`` to ``to`` (shares
            of the training)."""
            return lambda epoch: done + (to - done) * (epoch - lo) / max(hi - lo, 1)

        def turn(bounce: bool, before: int, epoch: int) -> Callable[[float], float]:
            """The ``place`` of the epochs ``before``..``epoch`` of the fit with or without the ``bounce``,
            which take turns: the one with it first."""
            done = (2 * before - rest_from + (0 if bounce else epoch - before)) / total
            return segment(before, epoch, done, done + (epoch - before) / total)

        def with_or_without_bounce() -> tuple[list[dict[str, Any]], list[dict[str, float]], dict[str, Any]]:
            """From stage 1 on, the fit with a bounce of reflectance γ and the fit without, taken in turns to
            each of ``checks`` and compared there until one is kept (module docstring, ``BOUNCE_CHECKS``),
            which goes on alone to the last epoch. Its records and history, and what the choice saw."""
            nonlocal shadows
            start = FitState.take(problem, field, model, shadows, gains)
            usable_a = problem.events.usable.cpu().numpy()
            if detector.uses_surface:
                # the fit with the bounce takes the mask the detector gives a surface inter-reflection flattened
                shadows = self._detect_again(detector, detector_options, pre, problem, field, True)
                clock.lap("redetect_bounce")
            seen = {**self._bounce(pre, problem, field, model, shadows, gamma),
                    "cast_shadow_share_with": problem.diagnostics["cast_shadow_share"]}
            clock.lap("bounce_1")
            if seen["bounce_frame_share"] < MIN_BOUNCE_SHARE:
                start.restore(problem, field, model, gains)
                shadows = start.shadows
                # no second fit: this one spans the rest of the bar
                records, fitted = _to_end(fitting(1, 0.0, segment(rest_from, last_epoch, place_of(rest_from), 1.0)))
                return records, fitted, {"kept": False, **seen}
            # both fits are judged on the pairs both masks leave usable: neither gains by leaving more out
            # both lists ascend: a lookup table intersects them in order (np.intersect1d sorts them again, 1.3 s at 1024²)
            usable_b = problem.events.usable.cpu().numpy()
            in_a = np.zeros(problem.events.target.shape[0], dtype=bool)
            in_a[usable_a] = True
            compared = usable_b[in_a[usable_b]]
            weights = self._stage(preset, options, 0, options["seed"])
            pauses = tuple(epoch for epoch, _ in checks)
            fits = {bounce: fitting(1, gamma if bounce else 0.0, turn(bounce, rest_from, pauses[0]), pauses) for bounce in (True, False)}
            states: dict[bool, FitState] = {False: start}
            seen_at: list[dict[str, float]] = []
            before = rest_from
            for epoch, margin in checks:
                left: dict[bool, float] = {}
                for bounce in (True, False):
                    if bounce in states:
                        states[bounce].restore(problem, field, model, gains)
                        shadows = states[bounce].shadows
                    if epoch == pauses[0]:
                        next(fits[bounce])
                    else:
                        fits[bounce].send((turn(bounce, before, epoch), True))
                    left[bounce] = self._unexplained(problem, field, model, weights, compared)
                    clock.lap("unexplained")
                    if bounce:
                        states[True] = FitState.take(problem, field, model, shadows, gains)
                seen_at.append({"epoch": epoch, "unexplained_with": left[True], "unexplained_without": left[False]})
                ratio = left[True] / left[False] if left[False] > 0 else float("inf")
                if abs(ratio - (1.0 + BOUNCE_TOLERANCE)) > margin or epoch == last_epoch:
                    break
                # the fit without the bounce, in place now, is set aside only when both go on
                states[False] = FitState.take(problem, field, model, shadows, gains)
                before = epoch
            kept = left[True] <= (1.0 + BOUNCE_TOLERANCE) * left[False]
            fits[not kept].close()
            if kept:
                states[True].restore(problem, field, model, gains)
                shadows = states[True].shadows
            records, fitted = _to_end(fits[kept], segment(epoch, last_epoch, place_of(2 * epoch - rest_from), 1.0))
            return records, fitted, {"kept": kept, **seen, "unexplained_without": left[False], "unexplained_with": left[True],
                                     "decided_at_epoch": epoch, "checks": seen_at}

        with deterministic(torch.device(self.device)):
            field = build_field(preset, problem, model)
            clock.lap("field")
            records, fitted = _to_end(fitting(0, 0.0, place_of, until=1))
            stages += records
            history += fitted
            if len(spans) > 1:
                fixed = gamma if bouncing and mode == "on" else 0.0
                record = between(1, fixed)
                if comparing:
                    records, fitted, record["interreflection"] = with_or_without_bounce()
                else:
                    records, fitted = _to_end(fitting(1, fixed, place_of))
                stages += [record, *records]
                history += fitted
            self.shadows = shadows
            normal, fitted = _current(field, model)
            maps = {name: value.cpu().numpy() for name, value in fitted.items()}
            normal_np = normal.cpu().numpy()
        clock.lap("output")
        return self._result(problem, model, normal_np, maps, options["fill_unlit"], {
            **problem.diagnostics, "preset": preset.record(), "brdf": model.name,
            "shadow_detector": detector_entry.name, "shadow_options": detector_options, "stages": stages, "indirect": model.indirect,
            "threshold_sigma": sigma, "thresholds": gains[-1].record() if gains else None,
            "preprocess_seconds": seconds_pre, "seconds": clock.record(), "final_loss": history[-1] if history else None,
            "device": str(self.device), "preprocess": pre.diagnostics,
        })

    @staticmethod
    def _bounce(pre: Preprocessed, problem: Problem, field: nn.Module, model: FitModel, shadows: ShadowMask,
                reflectance: float) -> dict[str, float]:
        """``interreflection.remove_bounce`` of the current fit at ``reflectance``, on the height the
        detector integrated from the same normals when it just did (``integrated_height``)."""
        normal, maps = _current(field, model)
        height = integrated_height(pre.evidence.with_normal(_frame_normal(problem, normal)))
        return remove_bounce(problem, model, normal, maps, height, shadows, pre.light, pre.t0_us, pre.period_us, reflectance)

    @staticmethod
    def _unexplained(problem: Problem, field: nn.Module, model: FitModel, config: StageConfig, pairs: np.ndarray) -> float:
        """``interreflection.unexplained`` of the current fit over ``pairs``, with the stages' loss weights."""
        return unexplained(problem, model, *_current(field, model), config.frame_weight, config.event_weight, config.event_huber,
                           pairs)

    @staticmethod
    def _stage(preset: Preset, options: dict[str, Any], epochs: int, seed: int) -> StageConfig:
        return StageConfig(
            epochs=epochs, lr=preset.lr, material_lr=preset.material_lr, frame_weight=options["frame_weight"],
            event_weight=preset.event_weight, event_huber=options["event_huber"],
            indirect_sparsity=options["indirect_sparsity"], tv_weight=preset.tv_weight,
            tv_fraction=preset.tv_fraction,
            event_batch=options["event_batch"], batch_pixels=preset.batch_pixels, tile=8, seed=seed,
            compiled=options["compile"],
        )

    @staticmethod
    def _detect_again(detector: ShadowDetector, detector_options: dict[str, Any], pre: Preprocessed, problem: Problem,
                      field: nn.Module, inter_reflected: bool) -> ShadowMask:
        """The detector on the current normals, told whether inter-reflected light is taken out, its mask
        into the problem."""
        with torch.no_grad():
            normal = field()[0]
        evidence = pre.evidence.with_normal(_frame_normal(problem, normal), fitted=True, inter_reflected=inter_reflected)
        shadows = detector.detect(evidence, detector_options)
        problem.apply_mask(shadows)
        return shadows

    @staticmethod
    def _restart(pre: Preprocessed, problem: Problem, field: nn.Module, model: FitModel, shadows: ShadowMask,
                 positions: np.ndarray) -> None:
        """Restart the masked pixels at ``positions`` (among the P) of a pyramid field from the closed
        form under ``shadows`` (a network cannot restart single pixels: left as is)."""
        if not isinstance(field, PyramidField) or positions.size == 0:
            return
        h, w, pixels = problem.geometry.height, problem.geometry.width, problem.geometry.pixels
        only = np.zeros(h * w, dtype=bool)
        only[pixels[positions]] = True
        init = pre.closed_form(shadows, only.reshape(h, w))
        n, albedo = start_values(init.normal, init.albedo, pixels[positions], problem.albedo_scale)
        index = torch.as_tensor(positions, dtype=torch.int64, device=problem.device)
        field.reset(index, torch.as_tensor(n, dtype=problem.dtype, device=problem.device),
                    model.pixel_raw_from(torch.as_tensor(albedo, dtype=problem.dtype, device=problem.device)))

    @staticmethod
    def _gated_pixels(problem: Problem, restart: np.ndarray) -> np.ndarray:
        """Positions among the P masked frame pixels that read the event pixels ``restart`` (He·We,)
        bool for at least half of their bilinear weight."""
        index, weight = problem.geometry.grid_taps
        share = np.sum(restart[index.cpu().numpy()] * weight.cpu().numpy(), axis=1)
        return np.flatnonzero(share >= 0.5)

    @staticmethod
    def _result(problem: Problem, model: FitModel, normal: np.ndarray, maps: dict[str, np.ndarray], fill: bool,
                diagnostics: dict[str, Any]) -> SolverResult:
        h, w, pixels = problem.geometry.height, problem.geometry.width, problem.geometry.pixels

        def full(values: np.ndarray) -> np.ndarray:
            out = np.zeros((h * w,) + values.shape[1:], dtype=np.float32)
            out[pixels] = values
            return out.reshape((h, w) + values.shape[1:])

        def squeeze(values: np.ndarray) -> np.ndarray:
            return values[..., 0] if values.ndim == 2 and values.shape[1] == 1 else values

        radiometric = {p.name for p in model.brdf.fit if p.radiometric}
        out = {name: full(squeeze(value) * (problem.albedo_scale if name in radiometric else 1.0)) for name, value in maps.items()}
        # derived maps are computed on reflectances relative to the capture's albedo scale
        out.update({name: full(squeeze(value)) for name, value in model.brdf.derived_maps(maps).items()})
        out["cast_shadow"] = problem.shadow_fraction.astype(np.float32)
        lit = np.zeros(h * w, dtype=bool)
        lit[pixels] = True
        lit = lit.reshape(h, w)
        unlit = unlit_pixels(lit) if fill else np.zeros_like(lit)
        out["unlit"] = unlit.astype(np.float32)
        diagnostics["unlit_pixels"] = int(np.count_nonzero(unlit))
        return SolverResult(normal=fill_unlit(full(normal), lit, unlit), mask=lit | unlit, maps=out, diagnostics=diagnostics)
