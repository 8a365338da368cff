"""The event-camera rule shared by the simulator (``pstoolkit.sim.esim``, ``pstoolkit.sim.ring_engine``) and the
event-based solvers.

A pixel sees the log-irradiance ``L(t) = ln(I(t) + ε)`` (``I`` linear grey irradiance, ``ε`` =
``LOG_EPS`` unless stated) and keeps a reference level ``L_ref``. It fires event ``k`` at ``t_k`` with
polarity ``p_k = +1`` when ``L`` has risen ``C⁺`` above the reference, ``p_k = −1`` when it has fallen
``C⁻`` below it (``C^{p}`` below is ``C⁺`` for ``p = +1`` and ``C⁻`` for ``p = −1``). The reference
at the start of a recording is the level then: ``L_ref,1 = L(t_start)``. After each event the pixel
is blind for the refractory period ``R``; what happens then is one of two rules
(``REFRACTORY_RULES``, see docs/sensors.md for the sensors and simulators behind them):

**"reset-at-end"** (the rule of the DualResPS paper, eq. 6, with ``η`` = R; the default): nothing the
pixel would have seen while blind is emitted, and at ``t + R`` its reference is reset to the level
it sees then. Every event fires at a crossing, ``L(t_k) = L_ref,k + p_k·C^{p_k}``, with

    L_ref,k = L(t_{k−1} + R)      for k ≥ 2

so a solver relating consecutive events evaluates the earlier level at ``reference_time_us(t_prev,
R)``: ``L(t_k) − L(t_{k−1} + R) = p_k·C^{p_k}``. On a line of slope ``s`` a pixel fires every
``R + C/|s|``.

**"rate-limited"** (a pixel whose change persists keeps firing): the reference moves by
exactly one threshold per event, ``L_ref,k+1 = L_ref,k + p_k·C^{p_k}`` (ESIM's rule without a
refractory period), and the pixel is blind until ``t_k + R``. If at ``t_k + R`` the level is still beyond ``L_ref ± C`` it fires at once,
at ``t_k + R``, so a persisting change keeps firing at the refractory rate 1/R until the reference
has caught up; a lag left over when the level turns back fires (in the old sense) every ``R`` while
the level stays beyond the moving threshold. An event that fired at a crossing (not at the end of
a blind time) satisfies

    L(t_k) = L(t_start) + Σ_{j≤k} p_j·C^{p_j}

so two such events j < k of a pixel satisfy ``L(t_k) − L(t_j) = Σ_{j<i≤k} p_i·C^{p_i}`` — the events
between them count whether or not they were exact. An event fired at the end of a blind time
(``t_k − t_{k−1} = R`` within the timestamp resolution) only bounds the level: ``p_k·(L(t_k) −
L_ref,k) ≥ C^{p_k}``. ``exact_pairs`` gives the exact pairs of either rule.

With ``R = 0`` both rules are ESIM's: the reference moves to the crossed level.

``ε = 1e-3`` assumes irradiance normalised to about 1 for a bright pixel (the 99th-percentile
normalisation of the semi-real recipe): the log stays finite in attached shadow (``ln ε ≈ −6.9``)
while shifting a lit pixel's log level by less than 0.1 %.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from psfmt import REFRACTORY_RULES, Calibration, EventArray
from pstoolkit.errors import UserError

LOG_EPS = 1e-3
REFRACTORY_RULE = REFRACTORY_RULES[0]
"""The default rule, and the rule of a capture that records none."""
TIMESTAMP_RESOLUTION_US = 1.0
"""Event times are whole µs: an event of the rate-limited rule fired at the end of a blind time
follows the one before by R to within this."""


def check_rule(rule: str, caller: str) -> str:
    """``rule`` if it is one of ``REFRACTORY_RULES``, else UserError naming ``caller``."""
    if rule not in REFRACTORY_RULES:
        raise UserError(f"{caller}: refractory rule {rule!r} is not one of {', '.join(REFRACTORY_RULES)}")
    return rule


def capture_rule(calibration: Calibration, caller: str) -> str:
    """A capture's refractory rule (``/calibration@refractory_rule``; absent: the format's default,
    ``REFRACTORY_RULE``), or a UserError naming ``caller`` for a rule not in ``REFRACTORY_RULES``."""
    return check_rule(calibration.refractory_rule or REFRACTORY_RULE, caller)


def log_irradiance(irradiance: np.ndarray, eps: float = LOG_EPS, dtype: type = np.float64) -> np.ndarray:
    """``ln(I + ε)``, the quantity whose changes fire events, computed in ``dtype``."""
    return np.log(np.asarray(irradiance, dtype=dtype) + dtype(eps))


def reference_time_us(t_prev_us: np.ndarray, refractory_us: float) -> np.ndarray:
    """When the reference level of the event after one at ``t_prev_us`` was taken under the
    "reset-at-end" rule: ``t_prev + R`` (µs)."""
    return np.asarray(t_prev_us, dtype=np.float64) + float(refractory_us)


@dataclass
class EventPairs:
    """Consecutive events of the same pixel: ``pixel`` = y·width + x, the earlier event's time
    ``t_prev_us``, the later event's time ``t_us`` and polarity ``p``; grouped by pixel, in time
    order within a pixel."""

    pixel: np.ndarray
    t_prev_us: np.ndarray
    t_us: np.ndarray
    p: np.ndarray


def _by_pixel(events: EventArray, width: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel (y·width + x), time and polarity of a time-sorted stream, grouped by pixel; a stable
    sort keeps each pixel's events in time order."""
    pixel = events.y.astype(np.int64) * width + events.x.astype(np.int64)
    order = np.argsort(pixel, kind="stable")
    return pixel[order], events.t[order], events.p[order]


def consecutive_pairs(events: EventArray, width: int) -> EventPairs:
    """Every (previous, current) event pair of each pixel of a time-sorted stream; a pixel's first
    event has no pair (its reference is the level at the start of the recording)."""
    pixel, t, p = _by_pixel(events, width)
    same = pixel[1:] == pixel[:-1]
    return EventPairs(pixel=pixel[1:][same], t_prev_us=t[:-1][same], t_us=t[1:][same], p=p[1:][same])


@dataclass
class LevelPairs:
    """Pairs of times of one pixel whose log levels differ by a known amount (``exact_pairs``):
    ``pixel`` = y·width + x, the earlier time ``t_ref_us`` (float µs), the later event's time
    ``t_us``, the numbers of positive and negative thresholds between them ``n_pos``/``n_neg``, and
    ``delta_log`` = L(t_us) − L(t_ref_us) = n_pos·C⁺ − n_neg·C⁻; grouped by pixel, in time order
    within a pixel. With per-pixel thresholds, ``n_pos`` and ``n_neg`` give the change as well."""

    pixel: np.ndarray
    t_ref_us: np.ndarray
    t_us: np.ndarray
    n_pos: np.ndarray
    n_neg: np.ndarray
    delta_log: np.ndarray


def exact_pairs(
    events: EventArray,
    width: int,
    rule: str,
    refractory_us: float,
    contrast_pos: float,
    contrast_neg: float,
    t_start_us: float | None = None,
) -> LevelPairs:
    """The pairs of a time-sorted event stream whose log change is exact under ``rule`` (see the
    module docstring):

    - "reset-at-end" (or R = 0): every event and the one before it of its pixel, the earlier level
      read at ``t_prev + R``; one threshold of the later event's polarity.
    - "rate-limited": consecutive exact events of a pixel — those that fired at a crossing, i.e.
      later than ``R + TIMESTAMP_RESOLUTION_US`` after the pixel's event before (an event at the end
      of a blind time only bounds the level) — with every threshold of the events after the earlier
      one up to the later one.

    Parameters
    ----------
    events
        Time-sorted event stream.
    width
        The sensor's width in pixels (pixel index y·width + x).
    rule
        One of ``REFRACTORY_RULES``.
    refractory_us
        The refractory period R, µs.
    contrast_pos, contrast_neg
        Thresholds C⁺ and C⁻ on the change of L.
    t_start_us
        Start of the recording, µs (default: the stream's first time); "rate-limited" only. A pixel's
        first event is exact when it comes later than ``R + TIMESTAMP_RESOLUTION_US`` after it, as no
        event before the recording can have left the pixel blind then.

    Returns
    -------
    LevelPairs
        The exact pairs, grouped by pixel, in time order within a pixel.

    Raises
    ------
    UserError
        An unknown rule.
    """
    check_rule(rule, "exact_pairs")
    pixel, t, p = _by_pixel(events, width)
    positive = (p > 0).astype(np.int64)
    if rule == REFRACTORY_RULES[0] or refractory_us == 0:
        same = pixel[1:] == pixel[:-1]
        n_pos, n_neg = positive[1:][same], 1 - positive[1:][same]
        return LevelPairs(pixel[1:][same], reference_time_us(t[:-1][same], refractory_us), t[1:][same], n_pos, n_neg,
                          n_pos * float(contrast_pos) - n_neg * float(contrast_neg))
    first = np.ones(len(t), dtype=bool)
    first[1:] = pixel[1:] != pixel[:-1]
    gap = np.empty(len(t))
    start = (float(t.min()) if len(t) else 0.0) if t_start_us is None else float(t_start_us)
    gap[first] = t[first] - start
    gap[~first] = np.diff(t)[~first[1:]]
    exact = np.flatnonzero(gap > refractory_us + TIMESTAMP_RESOLUTION_US)
    # thresholds crossed up to and including each event, counted from the stream's start
    crossed_pos, crossed = np.cumsum(positive), np.arange(1, len(t) + 1)
    later, earlier = exact[1:], exact[:-1]
    same = pixel[later] == pixel[earlier]
    later, earlier = later[same], earlier[same]
    n_pos = crossed_pos[later] - crossed_pos[earlier]
    n_neg = (crossed[later] - crossed[earlier]) - n_pos
    return LevelPairs(pixel[later], t[earlier].astype(np.float64), t[later], n_pos, n_neg,
                      n_pos * float(contrast_pos) - n_neg * float(contrast_neg))
