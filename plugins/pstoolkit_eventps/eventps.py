"""EventPS (Yu et al., CVPR 2024), the optimisation version, over an event stream: a normal at every
event pixel, for the whole stream or for each time window as the events arrive.

    from pstoolkit_eventps import eventps
    from pstoolkit.optics.lights import build_light_model

    params = eventps.Params(contrast_pos=0.15, contrast_neg=0.15, refractory_us=2000)
    light = build_light_model(capture.lights)
    for window in eventps.stream(capture.events.chunks(), light, capture.events.width,
                                 capture.events.height, params, window_us=33333):
        window.normal, window.confidence   # (H, W, 3) unit normals, (H, W) source of each

``stream`` keeps each pixel's last event between chunks and windows, so a pair whose events straddle a
chunk or window boundary counts, in the window of its later event; it holds one window's events at a
time (the whole stream when ``window_us`` is None), and ``threads=2`` fits windows on two cores while
the caller's thread pairs the next. ``solve`` gives the whole stream's map and its windows' maps from
one pass (the ``eventps`` solver's windowed mode).

Per window, the events pair by the refractory rule of ``params.refractory_rule``
(``pstoolkit.events.rule``; a capture records it in ``/calibration@refractory_rule``):

- "reset-at-end" (the paper's): consecutive events k−1, k of a pixel give n·v = 0 with
  v = e^{C⁺} l(t_ref) − l(t_k) for p_k = +1 and v = l(t_ref) − e^{C⁻} l(t_k) for p_k = −1 (facts of the
  paper; l the grey light, ``pstoolkit.events.relation``), t_ref = t_{k−1} + R being when the sensor
  took its reference level (the one EventPS's code applies when it evaluates the previous light at the
  last timestamp plus the refractory period).
- "rate-limited": only events that fired at a crossing (more than R after the pixel's previous event)
  are exact; consecutive exact events j < k give n·(e^{Δ/2} l(t_j) − e^{−Δ/2} l(t_k)) = 0 with
  Δ = n⁺·C⁺ − n⁻·C⁻ the thresholds of every event after j up to k. An event fired at the end of a
  blind time only bounds the change since the last exact one, p·(L(t) − L(t_j)) ≥ p·Δ: a half-space
  n·w ≥ 0.

Relations whose span lies outside [``min_interval_us``, ``max_interval_us``] are dropped, as in the
paper. A pixel with at least ``min_pairs`` exact constraints of rank 2 gets the smallest eigenvector of
Σ w v vᵀ (``relation_kernel.robust_fit``); the others get a normal from the swing of the ring light or
from their neighbours (``pstoolkit_eventps.fill``), and ``confidence`` says which (``eventfill.FIT``,
``NEIGHBOURS``, ``SWING``). Under "rate-limited" a pixel that fired but has no fit starts from its
neighbours and is refined by its own exact constraints and bounds (``relation_kernel.bounded_fit``),
restarting from its neighbourhood's mean ``BOUND_SMOOTHING`` times.

A fit more than ``eventfill.OUTLIER_DEG`` from the mean of its eight neighbours' normals is an
isolated outlier and takes that mean (confidence ``NEIGHBOURS``).

Sensor noise: a pixel firing far more than its neighbours is hot (``eventfill.hot_pixels``): its
events are left out and it takes its neighbours' normal. Under a ring light over whole turns C⁺/C⁻ is
set from the polarities of the events (``balanced_contrasts``, keeping the calibration's mean), which
corrects a calibration whose thresholds differ per polarity; the mean threshold, and a pixel's own
threshold, are not identifiable from its events (a scaled threshold trades against its tilt) and are
the calibration's. Events of background activity break the pairs they fall in; the Cauchy reweighting
rejects most of them.

Where this departs from the paper and its public code, and why:

- Weights. The paper leaves them open and its code sums the raw v vᵀ; here each v is weighted by
  min(1, a/ā)/|v|², a the arc the light travelled between the relation's two ends (``relation_kernel.light_arcs``) and ā
  the mean of its pixel's (``pair_weights`` "arc"): a highlight or a shadow edge fires a burst of short
  relations that break the Lambertian relation, and where the rest of the turn fires only a few (a
  shallow surface under the EVK4-like sensor's 0.5 ms refractory) the burst outvoted them; a relation
  longer than the mean counts once, as a long silence spans a peak, a trough or an attached shadow,
  where the relation is weakest. ``pair_weights`` "pairs" counts every relation once. Then
  ``reweight`` passes of iteratively reweighted least squares with Cauchy weights (scale
  ``residual_scale`` on n·v/|v|) follow (``benchmarks/baselines.py`` measures the choices).
- Pixels without a fit. The paper leaves them out; its code's solver (inverse power iteration on the
  adjugate with a small bias towards the camera axis, started at the axis) returns the axis for them.
  Here the swing or the neighbours give them a normal, marked in ``confidence``; ``fill=False`` leaves
  them at zero.
- A pixel's first event. The code's per-pixel timestamps start at zero, so a first event within the
  longest interval pairs with the light at the start of the recording; here it only sets the
  reference, as a real sensor's level before the recording began is unknown.
- Windows. The code keeps exponentially decaying sums per pixel for its live view; here windows are
  disjoint spans of ``window_us`` on the grid of its multiples, each solved from its own pairs.
- Both polarities may have their own threshold (C⁺, C⁻); the code uses one.
- Light. A directional light model of the capture (the code computes a near ring light's direction per
  pixel). The grey light is the direction times the luma of the light's RGB intensity: exact for a
  light of constant colour; a light whose colour changes over the turn on a coloured surface breaks
  the albedo cancellation. The relation also ignores the ε of ln(I + ε), so pixels lit at under a few
  per cent of their peak weigh in with a biased constraint.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from psfmt import REFRACTORY_RULES, EventArray
from pstoolkit._shared.vectors import unit
from pstoolkit.errors import UserError
from pstoolkit.events.relation import MIN_RANK_RATIO, constraint_vectors, grey_light
from pstoolkit.events.rule import REFRACTORY_RULE, check_rule
from pstoolkit.optics.lights import LightModel
from pstoolkit_eventps import fill as eventfill
from pstoolkit_eventps.relation_kernel import NO_EVENT, bounded_fit, capped_arc_weights, light_arcs, pair_events, robust_fit

PAIR_WEIGHTS = ("arc", "pairs")
"""How a relation counts in a pixel's fit (module docstring, "Weights")."""
MAX_INTERVAL_PERIODS = 0.5
"""Default longest pair interval under "reset-at-end", as a share of the light period: a pixel near the
ring's axis fires about once per half turn (its only pairs), while pairs that span a long attached
shadow are dropped."""
MAX_INTERVAL_PERIODS_RATE_LIMITED = 1.0
"""The same under "rate-limited", whose exact events are sparse (a pixel whose level changes faster
than C/R fires at the refractory rate, and those events only bound the level) and whose pairs keep
every threshold between them, however long: a whole turn."""
SWING_MIN_TURNS = 0.99
"""The swing argument needs a window of a full turn of the light (up to rounding its length to µs)."""
MAX_TABLE_US = 1_000_000
"""Longest light period (µs) whose light values are tabulated per µs (40 MB a second of period)."""
ADJUGATE_STEPS = 2
"""Power steps on the adjugate that refine a pixel's first normal and move it after each reweighting
(``eventkernel``)."""
BALANCE_MIN_EVENTS = 1000
"""Fewest rising and falling events ``balanced_contrasts`` needs (a share known to about 3 %)."""
GEOMETRY_SAMPLES = 3600
"""Samples of one light period to measure its zenith and whether it circles the axis."""


@dataclass(frozen=True)
class Params:
    """What the method needs besides the events and the light: contrast thresholds C⁺, C⁻ (log units),
    refractory period R (µs) and rule (``pstoolkit.events.rule.REFRACTORY_RULES``), the pair intervals
    used (µs; None: R and ``MAX_INTERVAL_PERIODS`` of the light period, or
    ``MAX_INTERVAL_PERIODS_RATE_LIMITED`` under "rate-limited", unlimited for an aperiodic light), the constraints a pixel needs for its own fit,
    the Cauchy reweighting passes and their scale, whether pixels without a fit get a normal, and
    whether C⁺/C⁻ is balanced by the events' polarities over whole turns (``balanced_contrasts``)."""

    contrast_pos: float
    contrast_neg: float
    refractory_us: float
    refractory_rule: str = REFRACTORY_RULE
    min_interval_us: float | None = None
    max_interval_us: float | None = None
    min_pairs: int = 3
    reweight: int = 3
    residual_scale: float = 0.03
    fill: bool = True
    balance: bool = True
    pair_weights: str = "arc"

    def __post_init__(self) -> None:
        if not (self.contrast_pos > 0 and self.contrast_neg > 0):
            raise ValueError(f"contrast thresholds must be positive, got {self.contrast_pos} and {self.contrast_neg}")
        if self.refractory_us < 0 or self.min_pairs < 2 or self.reweight < 0 or not self.residual_scale > 0:
            raise ValueError("refractory_us ≥ 0, min_pairs ≥ 2, reweight ≥ 0 and residual_scale > 0 are required")
        check_rule(self.refractory_rule, "eventps")
        if self.pair_weights not in PAIR_WEIGHTS:
            raise ValueError(f"pair_weights must be one of {', '.join(PAIR_WEIGHTS)}, got {self.pair_weights!r}")

    @property
    def rate_limited(self) -> bool:
        """Whether events pair by the "rate-limited" rule (with R = 0 both rules are the same)."""
        return self.refractory_rule == REFRACTORY_RULES[1] and self.refractory_us > 0

    def intervals(self, period_us: float | None) -> tuple[float, float]:
        """The shortest and longest pair interval used (µs)."""
        shortest = self.refractory_us if self.min_interval_us is None else self.min_interval_us
        if self.max_interval_us is not None:
            return shortest, self.max_interval_us
        share = MAX_INTERVAL_PERIODS_RATE_LIMITED if self.rate_limited else MAX_INTERVAL_PERIODS
        return shortest, share * period_us if period_us else math.inf


@dataclass
class NormalWindow:
    """The normals of one window [``start_us``, ``end_us``): ``normal`` (H, W, 3) float32 unit vectors
    at the event pixels (zero where none, with ``Params.fill`` off), ``confidence`` (H, W) float32
    (``eventfill.FIT``, ``NEIGHBOURS``, ``SWING``; 0 for none), the window's events, exact pairs,
    exact constraints kept, the thresholds C⁺, C⁻ used (``balanced_contrasts``) and the hot pixels
    left out (``eventfill.hot_pixels``)."""

    start_us: int
    end_us: int
    normal: np.ndarray
    confidence: np.ndarray
    events: int
    pairs: int
    constraints: int
    contrasts: tuple[float, float]
    hot: int

    def sources(self) -> dict[str, int]:
        """Pixels per source of their normal (``eventfill.SOURCES``)."""
        return {name: int(np.count_nonzero(self.confidence == level)) for name, level in eventfill.SOURCES.items()}


@dataclass
class PairedWindow:
    """A window after pairing (``WindowSolver.pair``): its span and turns of the light, its events,
    pairs, relations (flat pixel (m,), grey light at the reference (m, 3) and at the later event
    (m, 3), positive and negative thresholds crossed in between (m, 2), 0 for an exact relation or the
    sign of a bound (m,) int8; ``relation_kernel.pair_events``),
    and per pixel the events fired, the rising ones and those fired at the end of a blind time (P, 3),
    and the sum of p·m(t) (P, 2) for the swing."""

    start_us: int
    end_us: int
    turns: float
    events: int
    pairs: int
    constraint_pixel: np.ndarray
    reference: np.ndarray
    later: np.ndarray
    crossed: np.ndarray
    bound: np.ndarray
    fired: np.ndarray
    swing: np.ndarray


class LightPath:
    """The light as the method needs it at event times: the grey light l(t) (``pstoolkit.events.relation.grey_light``)
    at each event and at the end of its refractory period, and the unit direction of the light's motion
    across the image plane (for the swing). A periodic light with a whole number of µs per period is
    tabulated once per µs of one period, which gives the same values as evaluating it; other lights are
    evaluated at each event. Also measures, for a periodic light, whether its direction circles the
    camera axis (``circles_axis``) and the mean tangent of its zenith angle (``tan_zenith``)."""

    def __init__(self, light: LightModel, refractory_us: float) -> None:
        if light.near:
            raise UserError(f"eventps: light model {light.name!r} is a near light; eventps needs a directional one")
        self.light = light
        self.refractory_us = float(refractory_us)
        self.period_us = light.period_us
        self.circles_axis = False
        self.tan_zenith = 0.0
        self._table: tuple[np.ndarray, np.ndarray] | None = None
        if not self.period_us:
            return
        if float(self.period_us).is_integer() and self.refractory_us.is_integer() and self.period_us <= MAX_TABLE_US:
            times = np.arange(int(self.period_us), dtype=np.float64)
            direction, _ = light.evaluate(times)
            self._table = (np.ascontiguousarray(grey_light(light, times).T), _motion(direction))
        direction, _ = light.evaluate(np.arange(GEOMETRY_SAMPLES) * (self.period_us / GEOMETRY_SAMPLES))
        radius = np.hypot(direction[:, 0], direction[:, 1])
        if np.all(direction[:, 2] > 0) and np.all(radius > 0):
            azimuth = np.arctan2(direction[:, 1], direction[:, 0])
            turn = np.angle(np.exp(1j * np.diff(np.append(azimuth, azimuth[0])))).sum() / (2.0 * np.pi)
            self.circles_axis = bool(abs(abs(turn) - 1.0) < 1e-6)
            self.tan_zenith = float(np.mean(radius / direction[:, 2]))

    def rows(self, t_us: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
        """The grey light and the light's motion for events at ``t_us`` (int µs) as
        ``eventkernel.pair_events`` reads them: tables of one period and the period (µs), or a row
        per event (l(t) then l(t + R)) and 0."""
        if self._table is not None:
            light, motion = self._table
            return light, motion, light.shape[0]
        t = np.asarray(t_us, dtype=np.float64)
        before, _ = self.light.evaluate(t - 1.0)
        later, _ = self.light.evaluate(t + 1.0)
        light = np.ascontiguousarray(grey_light(self.light, np.concatenate([t, t + self.refractory_us])).T)
        return light, np.ascontiguousarray(unit(later[:, :2] - before[:, :2])), 0




def _motion(direction: np.ndarray) -> np.ndarray:
    """Unit xy motion of a periodic table of light directions (T, 3), by central differences."""
    xy = direction[:, :2]
    return np.ascontiguousarray(unit(np.roll(xy, -1, axis=0) - np.roll(xy, 1, axis=0)))


def balanced_contrasts(fired: np.ndarray, contrast_pos: float, contrast_neg: float) -> tuple[float, float]:
    """C⁺ and C⁻ with the calibration's mean and the ratio of the events' polarities over whole turns
    of a periodic light (``fired`` (P, 3): events, rising ones, ones at the end of a blind time): a
    pixel's level returns to where it started, so its rising and falling thresholds add up to the same,
    N⁺·C⁺ ≈ N⁻·C⁻. Pixels that fired at the end of a blind time are left out (under "rate-limited" they
    may still lag their level when the recording ends), and so is a count too small to say more than
    the calibration (fewer than ``BALANCE_MIN_EVENTS``)."""
    steady = fired[:, 2] == 0
    rising, total = int(fired[steady, 1].sum()), int(fired[steady, 0].sum())
    if min(rising, total - rising) < BALANCE_MIN_EVENTS:
        return contrast_pos, contrast_neg
    mean = 0.5 * (contrast_pos + contrast_neg)
    ratio = (total - rising) / rising  # C⁺/C⁻
    return 2.0 * mean * ratio / (1.0 + ratio), 2.0 * mean / (1.0 + ratio)


BOUND_PRIOR = 1e-3
"""Weight of the pull towards a pixel's filled normal in ``relation_kernel.bounded_fit``: enough to pick
a normal where its own constraints leave it free, small against any one constraint (weight 1)."""
BOUND_PASSES = 20
"""Most passes of ``relation_kernel.bounded_fit``."""
BOUND_SMOOTHING = 100
"""Rounds of ``_bounded`` that restart each refined pixel from the mean of its and its neighbours'
normals: where a pixel's own constraints leave its normal free, the surface's smoothness carries
the fits at the edge of a steep region inwards (blobs 128 px, rate-limited 2 ms: 7.3° with none,
6.2° with 10 rounds, 5.55° with 100, 5.52° with 200; a 5×5 mean instead of 3×3 does worse)."""


def _bounded(normal: np.ndarray, todo: np.ndarray, exact_pixel: np.ndarray, u: np.ndarray, exact_weight: np.ndarray,
             bound_pixel: np.ndarray, w: np.ndarray, shape: tuple[int, int], scale: float) -> None:
    """Refines the filled normals (P, 3) of the pixels ``todo`` in place with their own exact
    constraints (n·u = 0, weighted by ``exact_weight``) and bounds (n·w ≥ 0) (``relation_kernel.bounded_fit``,
    Cauchy ``scale``), then
    ``BOUND_SMOOTHING`` times again from the mean of their neighbourhood (``eventfill.neighbour_mean``
    on the (H, W) grid ``shape``)."""
    exact_order, bound_order = np.argsort(exact_pixel, kind="stable"), np.argsort(bound_pixel, kind="stable")
    exact_pixel, u = exact_pixel[exact_order], np.ascontiguousarray(u[exact_order])
    exact_weight = np.ascontiguousarray(exact_weight[exact_order])
    bound_pixel, w = bound_pixel[bound_order], np.ascontiguousarray(w[bound_order])
    neighbourhood = eventfill.neighbourhoods(todo, shape)
    for step in range(BOUND_SMOOTHING + 1):
        if step:
            normal[todo] = eventfill.neighbour_mean(normal, neighbourhood)
        bounded_fit(normal, todo, exact_pixel, u, exact_weight, bound_pixel, w, BOUND_PRIOR, BOUND_PASSES, scale)


class WindowSolver:
    """Solves windows of one event stream: pairs them in time order, keeping each pixel's last event
    between them, and fits each paired window on its own."""

    def __init__(self, light: LightModel, width: int, height: int, params: Params) -> None:
        self.path = LightPath(light, params.refractory_us)
        self.width, self.height = int(width), int(height)
        self.params = params
        self.min_interval_us, self.max_interval_us = params.intervals(light.period_us)
        pixels = self.width * self.height
        self.last_t = np.full(pixels, NO_EVENT, dtype=np.int64)
        self.anchor_t = np.full(pixels, NO_EVENT, dtype=np.int64)
        self.anchor_light = np.zeros((pixels, 3))
        self.crossed = np.zeros((pixels, 2), dtype=np.int64)
        self.start_us: int | None = None
        """The stream's first event: a pixel's first event is exact under "rate-limited" when it
        comes later than R after it (``pstoolkit.events.rule.exact_pairs``)."""

    def turns(self, span_us: float) -> float:
        """Turns of the light in ``span_us`` (0 for an aperiodic light)."""
        return span_us / self.path.period_us if self.path.period_us else 0.0

    def pair(self, events: EventArray, start_us: int, end_us: int, turns: float) -> PairedWindow:
        """The constraints of the window [start_us, end_us) holding ``events`` (time-ordered), over which
        the light made ``turns`` turns; windows must come in time order, as each pixel's last event
        carries over to the next. An event outside the sensor is a UserError."""
        params = self.params
        pixels = self.width * self.height
        if len(events) and (int(events.x.max()) >= self.width or int(events.y.max()) >= self.height):
            raise UserError(f"eventps: an event lies outside the {self.width}×{self.height} sensor")
        if self.start_us is None and len(events):
            self.start_us = int(events.t[0])
        light, motion, period = self.path.rows(events.t)
        fired = np.zeros((pixels, 3), dtype=np.int64)
        swing = np.zeros((pixels, 2))
        constraint_pixel, reference, later, crossed, bound, pairs = pair_events(
            events.x, events.y, events.t, events.p, self.width, light, motion, period, int(self.path.refractory_us),
            params.rate_limited, self.start_us or 0, self.last_t, self.anchor_t, self.anchor_light, self.crossed,
            float(self.min_interval_us), float(self.max_interval_us), fired, swing,
        )
        return PairedWindow(int(start_us), int(end_us), turns, len(events), int(pairs), constraint_pixel, reference,
                            later, crossed, bound, fired, swing)

    def _weights(self, paired: PairedWindow, kept: np.ndarray, exact: np.ndarray, pixel: np.ndarray) -> np.ndarray:
        """The weight of each kept exact relation, at flat pixels ``pixel`` (``Params.pair_weights``): 1, or
        min(1, a/ā) with a the light's arc between its ends (``relation_kernel.light_arcs``) and ā the mean
        arc of its pixel's."""
        if self.params.pair_weights == "pairs" or not len(pixel):
            return np.ones(len(pixel))
        arc = light_arcs(paired.reference, paired.later)[kept][exact]
        return capped_arc_weights(pixel, arc, self.width * self.height)

    def finish(self, paired: PairedWindow) -> NormalWindow:
        """The normals of a paired window: each pixel's own fit, and for the others the swing of the
        ring (from one turn of a light circling the axis) or their neighbours. Touches no state, so
        windows may be finished in parallel."""
        params = self.params
        pixels = self.width * self.height
        hot = eventfill.hot_pixels(paired.fired[:, 0], (self.height, self.width))
        fired = np.where(hot, 0, paired.fired[:, 0]) if hot.any() else paired.fired[:, 0]
        contrast_pos, contrast_neg = params.contrast_pos, params.contrast_neg
        if params.balance and self.path.circles_axis and paired.turns >= SWING_MIN_TURNS:
            contrast_pos, contrast_neg = balanced_contrasts(paired.fired[~hot], contrast_pos, contrast_neg)
        vectors, kept = constraint_vectors(paired.reference, paired.later, paired.crossed, contrast_pos, contrast_neg)
        if hot.any():
            kept &= ~hot[paired.constraint_pixel]
        pixel, bound, vectors = paired.constraint_pixel, paired.bound, vectors
        if not kept.all():
            pixel, bound, vectors = pixel[kept], bound[kept], vectors[kept]
        exact = bound == 0
        bounded = not exact.all()
        constraint_pixel, u = (pixel[exact], vectors[exact]) if bounded else (pixel, vectors)
        weight = self._weights(paired, kept, exact, constraint_pixel)
        normal, values, sums, count = robust_fit(
            constraint_pixel, u, weight, pixels, params.min_pairs, params.reweight, params.residual_scale, ADJUGATE_STEPS
        )
        fit = (count >= params.min_pairs) & (values[:, 1] > MIN_RANK_RATIO * values[:, 2])
        normal[~fit] = 0.0
        confidence = np.where(fit, eventfill.FIT, 0.0)
        rest = ~fit
        if params.fill and rest.any():
            swing = self.path.circles_axis and paired.turns >= SWING_MIN_TURNS
            if swing:
                contrast = 0.5 * (params.contrast_pos + params.contrast_neg)
                normal[rest] = eventfill.swing_normals(
                    fired[rest], paired.swing[rest], paired.turns, contrast, self.path.tan_zenith
                )
                confidence[rest] = eventfill.SWING
            # under "rate-limited" a pixel that fires at the refractory rate lags its level, so its event
            # count no longer measures its swing: its neighbours' constraints are the better start
            need = rest if not swing else rest & ((fired > 0) & params.rate_limited | hot)
            if need.any():
                filled, found = eventfill.neighbour_normals(sums, count, need, (self.height, self.width), params.min_pairs)
                normal[found] = filled[found]
                confidence[found] = eventfill.NEIGHBOURS
                if not swing:
                    normal[need & ~found] = eventfill.AXIS
                    confidence[need & ~found] = eventfill.SWING
            if bounded:
                _bounded(normal, np.flatnonzero(rest & (fired > 0)), constraint_pixel, u, weight, pixel[~exact],
                         -bound[~exact, None] * vectors[~exact], (self.height, self.width), params.residual_scale)
            mean, outlier = eventfill.isolated_outliers(normal, fit, (self.height, self.width))
            normal[outlier] = mean[outlier]
            confidence[outlier] = eventfill.NEIGHBOURS
        shape = (self.height, self.width)
        return NormalWindow(
            start_us=paired.start_us,
            end_us=paired.end_us,
            normal=normal.reshape(shape + (3,)).astype(np.float32),
            confidence=confidence.reshape(shape).astype(np.float32),
            events=paired.events,
            pairs=paired.pairs,
            constraints=len(constraint_pixel),
            contrasts=(float(contrast_pos), float(contrast_neg)),
            hot=int(np.count_nonzero(hot)),
        )


def stream(
    chunks: Iterable[EventArray],
    light: LightModel,
    width: int,
    height: int,
    params: Params,
    *,
    window_us: float | None = None,
    threads: int = 1,
) -> Iterator[NormalWindow]:
    """Normal maps of an event stream, one per time window, yielded in order once the events have
    passed the window's end (see the module docstring).

    Parameters
    ----------
    chunks
        Time-ordered chunks of events.
    light
        The light model; must be directional.
    width, height
        The sensor's size in pixels.
    params
        Thresholds, refractory period, pair intervals and fit options.
    window_us
        Window length, µs (> 0): one map per window [k·window_us, (k + 1)·window_us) from the first
        event's window to the last one's, empty windows included. None: one map for the whole stream,
        from its first event to its last, taken to cover the whole number of light turns nearest to that
        span (the stream is then held at once).
    threads
        With more than 1, the pairing stays in the caller's thread and up to ``threads`` windows are
        fitted at once in a pool (the compiled loops release the GIL): the same maps, sooner, each
        yielded up to ``threads`` windows later.

    Yields
    ------
    NormalWindow
        The normals of one window (H, W, 3) and their sources (H, W).

    Raises
    ------
    UserError
        A chunk that goes back in time, an event outside the sensor, or a near light.
    ValueError
        ``window_us`` not positive.
    """
    solver = WindowSolver(light, width, height, params)
    if window_us is None:
        events = EventArray.concatenate([chunk for chunk in chunks if len(chunk)])
        _check_sorted(events.t, None)
        first, last = (events.t_first_us or 0), (events.t_last_us or 0)
        # a recording under a periodic light covers whole turns; its first and last events lie inside them
        yield solver.finish(solver.pair(events, first, last + 1, float(round(solver.turns(last - first)))))
        return
    if not window_us > 0:
        raise ValueError(f"window_us must be positive, got {window_us}")
    windows = (solver.pair(*window) for window in _windows(chunks, window_us, solver))
    if threads <= 1:
        yield from map(solver.finish, windows)
        return
    with ThreadPoolExecutor(max_workers=threads) as pool:
        pending: deque[Future[NormalWindow]] = deque()
        for paired in windows:
            pending.append(pool.submit(solver.finish, paired))
            if len(pending) > threads:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()


def solve(
    chunks: Iterable[EventArray],
    light: LightModel,
    width: int,
    height: int,
    params: Params,
    *,
    window_us: float,
    threads: int = 1,
) -> tuple[NormalWindow, list[NormalWindow]]:
    """The map of the whole stream and the maps of its windows (as ``stream`` gives them) from one
    pairing pass: the whole stream's pairs are its windows' pairs, so its map is the one ``stream``
    gives with ``window_us`` None. Holds every constraint.

    Parameters
    ----------
    chunks, light, width, height, params
        As for ``stream``.
    window_us
        Window length, µs (> 0).
    threads
        The most maps fitted at once.

    Returns
    -------
    whole : NormalWindow
        The map of the whole stream.
    windows : list of NormalWindow
        The maps of its windows, in time order.

    Raises
    ------
    UserError
        A chunk that goes back in time, an event outside the sensor, or a near light.
    ValueError
        ``window_us`` not positive.
    """
    if not window_us > 0:
        raise ValueError(f"window_us must be positive, got {window_us}")
    solver = WindowSolver(light, width, height, params)
    pixels = solver.width * solver.height
    fired, swing = np.zeros((pixels, 3), dtype=np.int64), np.zeros((pixels, 2))
    relations: list[tuple[np.ndarray, ...]] = []
    first: int | None = None
    last = events_seen = pairs = 0
    with ThreadPoolExecutor(max_workers=max(1, threads)) as pool:
        futures = []
        for events, start_us, end_us, turns in _windows(chunks, window_us, solver):
            if len(events):
                first = events.t_first_us if first is None else first
                last = int(events.t[-1])
            paired = solver.pair(events, start_us, end_us, turns)
            futures.append(pool.submit(solver.finish, paired))
            fired += paired.fired
            swing += paired.swing
            relations.append((paired.constraint_pixel, paired.reference, paired.later, paired.crossed, paired.bound))
            events_seen, pairs = events_seen + paired.events, pairs + paired.pairs
        first = first or 0
        whole = PairedWindow(
            first,
            last + 1,
            float(round(solver.turns(last - first))),
            events_seen,
            pairs,
            *_joined(relations),
            fired,
            swing,
        )
        joined = pool.submit(solver.finish, whole)
        return joined.result(), [future.result() for future in futures]


def _joined(relations: list[tuple[np.ndarray, ...]]) -> tuple[np.ndarray, ...]:
    """The windows' relations (pixel, reference, later, crossed, bound) end to end."""
    if not relations:
        return np.empty(0, np.int64), np.empty((0, 3)), np.empty((0, 3)), np.empty((0, 2), np.int64), np.empty(0, np.int8)
    return tuple(np.concatenate(part) for part in zip(*relations))


def _windows(chunks: Iterable[EventArray], window_us: float, solver: WindowSolver) -> Iterator[tuple[EventArray, int, int, float]]:
    """(events, start_us, end_us, turns) of each window of the grid, in time order, once complete."""
    pending: list[EventArray] = []
    current: int | None = None
    last_t: int | None = None

    def window(k: int) -> tuple[EventArray, int, int, float]:
        events = pending[0] if len(pending) == 1 else EventArray.concatenate(pending)
        return events, round(k * window_us), round((k + 1) * window_us), solver.turns(window_us)

    for chunk in chunks:
        if not len(chunk):
            continue
        _check_sorted(chunk.t, last_t)
        last_t = int(chunk.t[-1])
        for k, lo, hi in _runs(chunk.t, window_us):
            if current is None:
                current = k
            while k > current:
                yield window(current)
                pending, current = [], current + 1
            pending.append(chunk[lo:hi])
    if current is not None:
        yield window(current)


def _window_index(t_us: np.ndarray | int, window_us: float) -> np.ndarray:
    """The window ⌊t / window_us⌋ of each time."""
    return np.floor(np.asarray(t_us) / window_us).astype(np.int64)


def _runs(t_us: np.ndarray, window_us: float) -> list[tuple[int, int, int]]:
    """(window, lo, hi) of the runs of sorted times ``t_us[lo:hi]`` in one window each, found by
    bisection on the window of each time (so exactly as ``_window_index`` assigns them)."""
    first, last = (int(k) for k in _window_index(t_us[[0, -1]], window_us))
    bounds = [0]
    for k in range(first + 1, last + 1):
        lo, hi = bounds[-1], len(t_us)
        while lo < hi:  # the first time in window k or later
            mid = (lo + hi) // 2
            if _window_index(int(t_us[mid]), window_us) >= k:
                hi = mid
            else:
                lo = mid + 1
        bounds.append(lo)
    bounds.append(len(t_us))
    return [(first + i, bounds[i], bounds[i + 1]) for i in range(len(bounds) - 1) if bounds[i + 1] > bounds[i]]


def _check_sorted(t_us: np.ndarray, previous: int | None) -> None:
    if (previous is not None and len(t_us) and t_us[0] < previous) or np.any(t_us[1:] < t_us[:-1]):
        raise UserError("eventps: the events are not in time order")
