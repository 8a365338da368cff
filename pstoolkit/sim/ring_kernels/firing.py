"""The event rule of ``pstoolkit.events.rule`` on the lanes' lines between samples, under either
refractory rule ("reset-at-end": ``fire_lanes``; "rate-limited": ``fire_lanes_paced``), and the
events' times on those lines (``emit``, ``emit_paced``). Every lane takes the same arithmetic, its
branches as selects, so the firing loops compile to SIMD; only lanes that fire store events."""

from __future__ import annotations

import math

import numba
import numpy as np

# Smallest normal double: slopes are floored at it so a flat line cannot divide by zero.
_TINY = np.finfo(np.float64).tiny

# Rows of ``fire_lanes``' output per lane: events, level of the first, level between them, the line's
# start level and 1/rise (all in the events' sense), and the sense (±1).
FIRE_COUNT, FIRE_FIRST, FIRE_GAP, FIRE_FROM, FIRE_INV_SPAN, FIRE_SIGN = range(6)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def fire_lanes(
    accepted: np.ndarray, ta: np.ndarray, la: np.ndarray, tb: np.ndarray, lb: np.ndarray, c_pos: np.ndarray,
    c_neg: np.ndarray, refractory_us: float, hi: np.ndarray, lo: np.ndarray, blind_until: np.ndarray,
    fire: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """The events of each ``accepted`` lane on the line from (``ta``, ``la``) to (``tb``, ``lb``) by
    the rule of ``pstoolkit.events.rule`` (as ``pstoolkit.sim.esim`` applies it to whole sensors): its firing
    state ``hi``, ``lo``, ``blind_until`` updated, and in ``fire`` (6, W) what ``emit`` needs to
    place them (rows ``FIRE_*``; no events: a count of 0). Every lane takes the same arithmetic, its
    branches as selects, so the loop compiles to SIMD; the slope is floored at the smallest normal
    double so a flat line cannot divide by zero."""
    for k in range(accepted.size):
        dt = tb[k] - ta[k]
        reset = accepted[k] and blind_until[k] <= tb[k]
        level = la[k] + (lb[k] - la[k]) * (blind_until[k] - ta[k]) / dt
        h = level + c_pos[k] if reset else hi[k]
        l = level - c_neg[k] if reset else lo[k]
        blind = np.inf if reset else blind_until[k]
        up = accepted[k] and lb[k] >= h
        fired = up or (accepted[k] and lb[k] <= l)
        sign = 1.0 if up else -1.0
        a, b = sign * la[k], sign * lb[k]
        first = h if up else -l
        gap = c_pos[k] if up else c_neg[k]
        slope = max((b - a) / dt, _TINY)
        gap = gap + slope * refractory_us if refractory_us > 0 else gap
        rise = (b - first) / gap if fired else 0.0
        count = math.floor(rise) + 1.0 if fired else 0.0
        last = first + (count - 1.0) * gap
        if refractory_us == 0:
            reference = sign * last
            blind_now = False
        else:
            until = min(ta[k] + (last - a) / slope, tb[k]) + refractory_us
            blind_now = until > tb[k]
            reference = sign * (last + slope * refractory_us)
            blind = until if fired and blind_now else blind
        hi[k] = (np.inf if blind_now else reference + c_pos[k]) if fired else h
        lo[k] = (-np.inf if blind_now else reference - c_neg[k]) if fired else l
        blind_until[k] = blind
        fire[FIRE_COUNT, k] = count
        fire[FIRE_FIRST, k] = first
        fire[FIRE_GAP, k] = gap
        fire[FIRE_FROM, k] = a
        fire[FIRE_INV_SPAN, k] = 1.0 / max(b - a, _TINY)
        fire[FIRE_SIGN, k] = sign


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def emit(
    fire: np.ndarray, k: int, ta: float, tb: float, out_t: np.ndarray, out_p: np.ndarray, n: int,
) -> int:  # pragma: no cover - compiled
    """Lane ``k``'s events from ``fire_lanes`` on its step from ``ta`` to ``tb``, stored in the rows
    ``out_t`` (whole µs, rounded half up)/``out_p`` after the ``n`` there as far as they have room;
    returns the pixel's event count."""
    count = np.int64(fire[FIRE_COUNT, k])
    first, gap, a, inv_span = fire[FIRE_FIRST, k], fire[FIRE_GAP, k], fire[FIRE_FROM, k], fire[FIRE_INV_SPAN, k]
    sign = np.int8(fire[FIRE_SIGN, k])
    for i in range(min(count, out_t.shape[0] - n)):
        frac = min(max((first + i * gap - a) * inv_span, 0.0), 1.0)
        out_t[n + i] = np.int64(math.floor(ta + frac * (tb - ta) + 0.5))
        out_p[n + i] = sign
    return n + count


# Rows of ``fire_lanes_paced``' output per lane, for each of its two runs (``PACED_ROWS`` apart):
# events, the first time the pixel may fire, the crossing of the first threshold, the time between
# thresholds on the line, and the sign; the k-th event (from 0) of a run is at
# max(start + k·R, crossing + k·spacing).
PACED_COUNT, PACED_START, PACED_CROSSING, PACED_SPACING, PACED_SIGN = range(5)
PACED_ROWS = 5


@numba.njit(cache=True, nogil=True, error_model="numpy")
def fire_lanes_paced(
    accepted: np.ndarray, ta: np.ndarray, la: np.ndarray, tb: np.ndarray, lb: np.ndarray, c_pos: np.ndarray,
    c_neg: np.ndarray, refractory_us: float, hi: np.ndarray, lo: np.ndarray, blind_until: np.ndarray,
    fire: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """The events of each ``accepted`` lane on the line from (``ta``, ``la``) to (``tb``, ``lb``) by
    the "rate-limited" rule of ``pstoolkit.events.rule`` (R = ``refractory_us`` > 0): its state
    ``hi``/``lo`` (reference ± C) and ``blind_until`` (end of the blind time) updated, and in ``fire``
    (2·``PACED_ROWS``, W) its two runs (rows ``PACED_*``; no events: counts of 0).

    On a line of slope s, a lane first fires what lags from before against the line (or on a flat
    one): if at t₁ = max(blind_until, ta) the level is beyond a threshold on the side the line moves
    away from, it fires there every R while the level, falling at |s| towards the threshold that
    moves C per event, stays beyond it: n₁ = ⌊(beyond at t₁)/(C + |s|·R)⌋ + 1 events, at most as many
    as fit before ``tb``. Then the line's own run: with t_c the (unclipped) time the line crosses the
    first threshold in its sense — before ``ta`` for a lag in that sense — and t₂ = max(blind_until,
    ta, t_c), the k-th event is at max(t₂ + (k − 1)·R, t_c + (k − 1)·C/|s|) (the later of the next
    time the pixel may fire and the k-th crossing; by induction on k, as both are arithmetic), as
    long as that is before ``tb``. Both runs fall in one step only if it is longer than R and moves
    the level by C or more, which the step control (``max_dlog`` = C/2) allows only at ``min_dt``
    (a jump, when R is shorter); both are kept. Every lane takes the same arithmetic, its branches
    as selects (SIMD)."""
    r = refractory_us
    for k in range(accepted.size):
        acc = accepted[k]
        slope = (lb[k] - la[k]) / (tb[k] - ta[k])
        speed = abs(slope)
        t1 = max(blind_until[k], ta[k])
        level = la[k] + slope * (t1 - ta[k])
        open_ = acc and t1 <= tb[k]
        up = open_ and level >= hi[k]
        down = open_ and level <= lo[k]
        sign1 = 1.0 if up else -1.0
        c1 = c_pos[k] if up else c_neg[k]
        beyond = sign1 * level - (hi[k] if up else -lo[k])
        n1 = min(math.floor(beyond / (c1 + speed * r)), math.floor((tb[k] - t1) / r)) + 1.0
        n1 = n1 if (up or down) and sign1 * slope <= 0.0 else 0.0
        shift = sign1 * n1 * c1
        h, l = hi[k] + shift, lo[k] + shift
        blind = t1 + n1 * r if n1 > 0.0 else blind_until[k]
        rising = slope > 0.0
        sign2 = 1.0 if rising else -1.0
        c2 = c_pos[k] if rising else c_neg[k]
        first = h if rising else -l
        inverse = 1.0 / max(speed, _TINY)
        crossing = ta[k] + (first - sign2 * la[k]) * inverse
        t2 = max(max(blind, ta[k]), crossing)
        n2 = min(math.floor((sign2 * lb[k] - first) / c2), math.floor((tb[k] - t2) / r)) + 1.0
        n2 = n2 if acc and slope != 0.0 and t2 <= tb[k] and sign2 * lb[k] >= first else 0.0
        spacing = c2 * inverse
        shift = sign2 * n2 * c2
        last = max(t2 + (n2 - 1.0) * r, crossing + (n2 - 1.0) * spacing)
        hi[k] = h + shift if acc else hi[k]
        lo[k] = l + shift if acc else lo[k]
        blind_until[k] = (last + r if n2 > 0.0 else blind) if acc else blind_until[k]
        fire[PACED_COUNT, k] = n1
        fire[PACED_START, k] = t1
        fire[PACED_CROSSING, k] = t1
        fire[PACED_SPACING, k] = 0.0
        fire[PACED_SIGN, k] = sign1
        fire[PACED_ROWS + PACED_COUNT, k] = n2
        fire[PACED_ROWS + PACED_START, k] = t2
        fire[PACED_ROWS + PACED_CROSSING, k] = crossing
        fire[PACED_ROWS + PACED_SPACING, k] = spacing
        fire[PACED_ROWS + PACED_SIGN, k] = sign2


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def emit_paced(
    fire: np.ndarray, k: int, refractory_us: float, out_t: np.ndarray, out_p: np.ndarray, n: int,
) -> int:  # pragma: no cover - compiled
    """Lane ``k``'s events from ``fire_lanes_paced``, its two runs in order, stored in the rows
    ``out_t`` (whole µs, rounded half up)/``out_p`` after the ``n`` there as far as they have room;
    returns the pixel's event count."""
    for run in range(2):
        row = run * PACED_ROWS
        count = np.int64(fire[row + PACED_COUNT, k])
        start, crossing, spacing = fire[row + PACED_START, k], fire[row + PACED_CROSSING, k], fire[row + PACED_SPACING, k]
        sign = np.int8(fire[row + PACED_SIGN, k])
        for i in range(min(count, max(out_t.shape[0] - n, 0))):
            t = max(start + i * refractory_us, crossing + i * spacing)
            out_t[n + i] = np.int64(math.floor(t + 0.5))
            out_p[n + i] = sign
        n += count
    return n
