"""The ``eventps`` solver: EventPS's optimisation method (``pstoolkit_eventps.eventps``, which states where it
departs from the paper and its public code) over a whole event stream, and optionally one normal map
per time window.

Every event pixel gets a normal: from its own pairs (a full rank-2 fit), or, for a pixel with too few
pairs, from the swing of the ring light over a turn (silence: the camera axis) or from its
neighbours' constraints (``pstoolkit_eventps.fill``). The ``confidence`` map says which, at the target
resolution: ``1`` fit, ``0.5`` neighbours, ``0.25`` swing, ``0`` outside the event sensor's view. Events
cannot tell a dark background from a surface facing the camera, so a background that fires nothing
gets the axis too; the mask is the sensor's view. When the target grid (frames or ground truth) differs
from the event sensor, normals are resampled through the calibration's event→frame affine
(``resample``), the confidence by nearest event pixel.

Runs on the CPU (numpy and numba) whatever ``--device`` says. The light model must be directional.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

import psfmt
from pstoolkit import Option, Progress, Solver, SolverResult, UserError, build_light_model
from pstoolkit.events.rule import capture_rule
from pstoolkit.solve.cluster import available_cpus, max_parallel
from pstoolkit_eventps import eventps
from pstoolkit_eventps.resample import Resampler, event_to_frame_affine

MAX_SEQUENCE_BYTES = 4 << 30
"""Largest ``normal_sequence`` the solver builds in memory; longer sequences belong to the stream API."""


def _contrasts(capture: psfmt.Capture, contrast: float, where: str) -> tuple[float, float]:
    if contrast > 0:
        return contrast, contrast
    cal = capture.calibration
    if cal.contrast_pos is None or cal.contrast_neg is None:
        raise UserError(f"eventps: {where} has no contrast threshold in its calibration; set one with --set contrast=C")
    return float(cal.contrast_pos), float(cal.contrast_neg)


def _check_sequence_size(stream: psfmt.EventArray, window_us: float, target: tuple[int, int]) -> None:
    """UserError when the windows' normal maps would not fit in ``MAX_SEQUENCE_BYTES``."""
    count = math.floor(int(stream.t[-1]) / window_us) - math.floor(int(stream.t[0]) / window_us) + 1
    size = count * target[0] * target[1] * 3 * 4
    if size > MAX_SEQUENCE_BYTES:
        raise UserError(
            f"eventps: window_us={window_us:g} gives {count} windows, {size / 2**30:.1f} GiB of normal maps "
            f"(at most {MAX_SEQUENCE_BYTES / 2**30:g} GiB); use longer windows, or pstoolkit_eventps.eventps.stream to take them one at a time"
        )


class EventPS(Solver):
    name = "eventps"
    summary = "EventPS optimisation: per-pixel smallest eigenvector of event-pair constraints, a normal at every pixel (CPU)"
    options = (
        Option("contrast", float, 0.0, "contrast threshold C in log units (0 = the capture's calibration)", minimum=0.0),
        Option("refractory_us", float, 0.0, "refractory period in µs (0 = the capture's calibration)", minimum=0.0),
        Option("min_interval_us", float, 0.0, "shortest pair interval used, µs (0 = the refractory period)", minimum=0.0),
        Option(
            "max_interval_us", float, 0.0,
            f"longest pair interval used, µs (0 = {eventps.MAX_INTERVAL_PERIODS:g} of the light period, "
            f"{eventps.MAX_INTERVAL_PERIODS_RATE_LIMITED:g} under the rate-limited rule; none for an aperiodic light)",
            minimum=0.0,
        ),
        Option("min_pairs", int, 3, "constraints a pixel needs for its own fit", minimum=2),
        Option("reweight", int, 3, "Cauchy reweighting passes of each pixel's fit (0 = plain least squares, as the paper)", minimum=0),
        Option("residual_scale", float, 0.03,
               "Cauchy scale of a constraint's residual n·v/|v| (the reweighting; also the bounded refinement under the rate-limited rule)",
               minimum=1e-6),
        Option("pair_weights", str, "arc",
               "how a relation counts in a pixel's fit: arc (by the arc the light travelled between its events, up to its "
               "pixel's mean arc, so a burst of events at a highlight or shadow edge does not outvote the rest of the "
               "turn) or pairs (each once)",
               choices=eventps.PAIR_WEIGHTS),
        Option("fill", bool, True, "give pixels without their own fit a normal from the ring's swing or their neighbours"),
        Option("balance", bool, True, "set the ratio C⁺/C⁻ from the events' polarities over whole turns of a ring light (keeping the mean C)"),
        Option(
            "window_us", float, 0.0,
            "also solve one normal map per window of this many µs (maps['normal_sequence']); 0 = off",
            minimum=0.0,
        ),
        Option("threads", int, 0, "maps fitted at once with window_us (0 = the cores this process may use)", minimum=0, maximum=max_parallel()),
    )
    needs = frozenset({"events", "lights"})
    requires = {"threads": ("window_us", "window_us > 0 (threads fit windows at once)"),
                "residual_scale": ("reweight", "reweight > 0 (the scale of the Cauchy reweighting)")}
    """Options read only when another one is positive: the option, the other, and why."""

    @classmethod
    def resolve_options(cls, options: dict[str, Any]) -> dict[str, Any]:
        """The options as given: their placeholders (0 = the capture's calibration, the refractory
        period, the light period, the cores) depend on the capture or the machine, and the run records
        what they became in its diagnostics. UserError for ``threads`` changed without ``window_us``
        and ``residual_scale`` changed with ``reweight=0``, which nothing would read."""
        for option in cls.options:
            if option.name in cls.requires and options[option.name] != option.default:
                other, why = cls.requires[option.name]
                if not options[other] > 0:
                    raise UserError(f"eventps: option {option.name}={options[option.name]:g} cannot apply with {other}=0: it needs {why}")
        return options

    def solve(self, capture: psfmt.Capture, options: dict[str, Any], progress: Progress) -> SolverResult:
        events = capture.events
        assert events is not None and capture.lights is not None
        where = str(capture.path or "the capture")
        light = build_light_model(capture.lights)
        contrast_pos, contrast_neg = _contrasts(capture, options["contrast"], where)
        params = eventps.Params(
            contrast_pos=contrast_pos,
            contrast_neg=contrast_neg,
            refractory_us=options["refractory_us"] or float(capture.calibration.refractory_us or 0.0),
            refractory_rule=capture_rule(capture.calibration, f"eventps: {where}"),
            min_interval_us=options["min_interval_us"] or None,
            max_interval_us=options["max_interval_us"] or None,
            min_pairs=options["min_pairs"],
            reweight=options["reweight"],
            residual_scale=options["residual_scale"],
            pair_weights=options["pair_weights"],
            fill=options["fill"],
            balance=options["balance"],
        )
        stream = events.read()
        target = psfmt.target_size(capture)
        windowed = options["window_us"] > 0 and len(stream) > 0
        if windowed:
            _check_sequence_size(stream, options["window_us"], target)
        progress(0.2, "events read")
        windows: list[eventps.NormalWindow] = []
        if windowed:
            whole, windows = eventps.solve(
                [stream], light, events.width, events.height, params,
                window_us=options["window_us"], threads=options["threads"] or available_cpus(),
            )
        else:
            (whole,) = eventps.stream([stream], light, events.width, events.height, params)
        progress(0.7, "normals")
        resample = Resampler(event_to_frame_affine(capture, target), (events.height, events.width), target)
        out_normal, out_mask = resample.normals(whole.normal, whole.confidence > 0)
        maps: dict[str, np.ndarray] = {"confidence": np.where(out_mask, resample.nearest(whole.confidence), 0.0)}
        shortest, longest = params.intervals(light.period_us)
        diagnostics: dict[str, Any] = {
            "events": whole.events,
            "pairs": whole.pairs,
            "constraints": whole.constraints,
            "contrast_pos": whole.contrasts[0],
            "contrast_neg": whole.contrasts[1],
            "hot_pixels": whole.hot,
            "refractory_us": params.refractory_us,
            "refractory_rule": params.refractory_rule,
            "min_interval_us": shortest,
            "max_interval_us": longest if np.isfinite(longest) else None,
            "event_size": [events.height, events.width],
            "sources": whole.sources(),
            "mask_pixels": int(np.count_nonzero(out_mask)),
        }
        if windowed:
            sequence = np.empty((len(windows),) + target + (3,), dtype=np.float32)
            for i, window in enumerate(windows):
                sequence[i] = resample.normals(window.normal, window.confidence > 0)[0]
            maps["normal_sequence"] = sequence
            diagnostics["window_us"] = options["window_us"]
            diagnostics["window_start_us"] = [w.start_us for w in windows]
        progress(1.0, "done")
        return SolverResult(normal=out_normal, mask=out_mask, maps=maps, diagnostics=diagnostics)
