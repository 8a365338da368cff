"""The ``eventps`` solver: EventPS's optimisation method (facts §5) over a whole event stream, or
one normal map per time window for real-time use.

Steps, all vectorised: one stable argsort groups the events by pixel in time order; consecutive
pairs give unit constraints v (``constraints.pair_constraints``); the six unique entries of Σ v vᵀ
are accumulated per pixel (and window) with ``np.bincount``; one batched ``np.linalg.eigh`` gives
each pixel's smallest eigenvector, flipped so n_z > 0. Pixels with fewer than ``min_pairs``
constraints, or constraints of rank < 2, are masked out. When the target grid (frames or ground
truth) differs from the event sensor, normals are resampled through the calibration's
event→frame affine (``resample.to_target``).

Runs in numpy on the CPU whatever ``--device`` says. The light model must be directional.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

import psfmt
from pstoolkit import Option, Solver, SolverResult
from pstoolkit.errors import UserError
from pstoolkit.eventnormals import Constraints, accumulate, smallest_eigenvectors
from pstoolkit.lights import LightModel, build_light_model
from pstoolkit.solver import Progress
from pstoolkit_eventps.constraints import pair_constraints
from pstoolkit_eventps.resample import event_to_frame_affine, to_target

# Pixel bins (windows × pixels) accumulated at once in windowed mode: 2²⁰ bins hold 72 MiB of sums.
WINDOW_BINS = 1 << 20
MAX_INTERVAL_PERIODS = 0.5
"""Default longest pair interval, as a share of the light period: a pixel near the ring's axis
fires about once per half turn (its only pairs), while pairs that span a long attached shadow are
dropped. On a simulated Lambertian sphere (128 px events, one turn) 0.25 loses most pixels with
|n_xy| < 0.3 (MAE 10.4° with them counted as 90°) and no limit lets shadow-spanning pairs bias the
rim (0.55° → 0.74° on the covered pixels); 0.5 gives 4.4° (cast-shadow marcher off)."""


def _contrasts(capture: psfmt.Capture, contrast: float, where: str) -> tuple[float, float]:
    if contrast > 0:
        return contrast, contrast
    cal = capture.calibration
    if cal.contrast_pos is None or cal.contrast_neg is None:
        raise UserError(f"eventps: {where} has no contrast threshold in its calibration; set one with --set contrast=C")
    return float(cal.contrast_pos), float(cal.contrast_neg)


def _max_interval(light: LightModel, max_interval_us: float) -> float:
    if max_interval_us > 0:
        return max_interval_us
    return MAX_INTERVAL_PERIODS * light.period_us if light.period_us else math.inf


def _solve_bins(bins: np.ndarray, constraints: Constraints, n_bins: int, min_pairs: int) -> tuple[np.ndarray, np.ndarray]:
    sums, counts = accumulate(bins, constraints, n_bins)
    return smallest_eigenvectors(sums, counts, min_pairs)


class EventPS(Solver):
    name = "eventps"
    summary = "EventPS optimisation: per-pixel smallest eigenvector of event-pair constraints (numpy, CPU)"
    options = (
        Option("contrast", float, 0.0, "contrast threshold C in log units (0 = the capture's calibration)", minimum=0.0),
        Option("refractory_us", float, 0.0, "refractory period in µs (0 = the capture's calibration)", minimum=0.0),
        Option("min_interval_us", float, 0.0, "shortest pair interval used, µs (0 = the refractory period)", minimum=0.0),
        Option(
            "max_interval_us", float, 0.0,
            f"longest pair interval used, µs (0 = {MAX_INTERVAL_PERIODS:g} of the light period; none for an aperiodic light)",
            minimum=0.0,
        ),
        Option("min_pairs", int, 2, "a pixel needs at least this many constraints", minimum=2),
        Option(
            "window_us", float, 0.0,
            "also solve one normal map per window of this many µs (maps['normal_sequence']); 0 = off",
            minimum=0.0,
        ),
    )
    needs = frozenset({"events", "lights"})

    def solve(self, capture: psfmt.Capture, options: dict[str, Any], progress: Progress) -> SolverResult:
        events = capture.events
        assert events is not None and capture.lights is not None
        where = str(capture.path or "the capture")
        light = build_light_model(capture.lights)
        if light.near:
            raise UserError(f"eventps: light model {light.name!r} is a near light; eventps needs a directional one")
        contrast_pos, contrast_neg = _contrasts(capture, options["contrast"], where)
        refractory = options["refractory_us"] or float(capture.calibration.refractory_us or 0.0)
        min_interval = options["min_interval_us"] or refractory
        max_interval = _max_interval(light, options["max_interval_us"])
        stream = events.read()
        progress(0.2, "events read")
        constraints, n_pairs = pair_constraints(
            stream,
            events.width,
            light,
            contrast_pos=contrast_pos,
            contrast_neg=contrast_neg,
            refractory_us=refractory,
            min_interval_us=min_interval,
            max_interval_us=max_interval,
        )
        progress(0.5, "constraints")
        n_pixels = events.width * events.height
        shape = (events.height, events.width)
        normal, ok = _solve_bins(constraints.pixel, constraints, n_pixels, options["min_pairs"])
        target = psfmt.target_size(capture)
        affine = event_to_frame_affine(capture, target)
        out_normal, out_mask = to_target(normal.reshape(shape + (3,)), ok.reshape(shape), affine, target)
        progress(0.7, "normals")

        maps: dict[str, np.ndarray] = {}
        diagnostics: dict[str, Any] = {
            "events": len(stream),
            "pairs": n_pairs,
            "constraints": len(constraints.weight),
            "contrast_pos": contrast_pos,
            "contrast_neg": contrast_neg,
            "refractory_us": refractory,
            "min_interval_us": min_interval,
            "max_interval_us": max_interval if math.isfinite(max_interval) else None,
            "event_size": [events.height, events.width],
            "event_mask_pixels": int(np.count_nonzero(ok)),
            "mask_pixels": int(np.count_nonzero(out_mask)),
        }
        if options["window_us"] > 0 and len(stream):
            (window_normal, window_ok), starts = self._windows(
                constraints, stream, options["window_us"], n_pixels, options["min_pairs"]
            )
            seq_normal, seq_mask = to_target(
                window_normal.reshape((-1,) + shape + (3,)), window_ok.reshape((-1,) + shape), affine, target
            )
            maps["normal_sequence"] = np.where(seq_mask[..., None], seq_normal, 0.0).astype(np.float32)
            diagnostics["window_us"] = options["window_us"]
            diagnostics["window_start_us"] = starts
        progress(1.0, "done")
        return SolverResult(normal=out_normal, mask=out_mask, maps=maps, diagnostics=diagnostics)

    @staticmethod
    def _windows(
        constraints: Constraints, stream: psfmt.EventArray, window_us: float, n_pixels: int, min_pairs: int
    ) -> tuple[tuple[np.ndarray, np.ndarray], list[int]]:
        """One normal map per window of ``window_us`` on the grid of its multiples covering the
        stream; a pair belongs to the window of its later event. Windows are solved in groups of
        about ``WINDOW_BINS`` pixel bins so memory stays bounded on long streams. Returns ((N, P, 3)
        normals, (N, P) masks) and the window start times (µs)."""
        first = math.floor(int(stream.t[0]) / window_us)
        count = math.floor(int(stream.t[-1]) / window_us) - first + 1
        window = np.floor(constraints.t_us / window_us).astype(np.int64) - first
        order = np.argsort(window, kind="stable")
        sorted_window = window[order]
        normal = np.zeros((count, n_pixels, 3))
        ok = np.zeros((count, n_pixels), dtype=bool)
        group = max(1, WINDOW_BINS // n_pixels)
        for start in range(0, count, group):
            stop = min(start + group, count)
            lo, hi = np.searchsorted(sorted_window, [start, stop])
            pick = order[lo:hi]
            part = Constraints(pixel=constraints.pixel[pick], t_us=constraints.t_us[pick], v=constraints.v[:, pick],
                               weight=constraints.weight[pick])
            bins = (window[pick] - start) * n_pixels + part.pixel
            n, determined = _solve_bins(bins, part, (stop - start) * n_pixels, min_pairs)
            normal[start:stop] = n.reshape(-1, n_pixels, 3)
            ok[start:stop] = determined.reshape(-1, n_pixels)
        starts = [round((first + i) * window_us) for i in range(count)]
        return (normal, ok), starts
