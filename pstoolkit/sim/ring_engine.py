"""The simulator's compiled engine: events and long exposures of a scene under a ring light in one
pass per event pixel (numba, in parallel over event pixels).

It covers what the simulator renders on the CPU with the built-in BRDFs (``ggx``, ``lambertian``):
a directional ring light, the closed-form shading of ``Renderer`` and the cast shadows of its shadow
grid. Other BRDFs, and other devices, go through ``Renderer`` and ``pstoolkit.sim.esim``; both follow the
same event rule (``pstoolkit.events.rule``) and ``tests/sim/test_simkernel.py`` compares them.

Per event pixel, time advances in its own steps (ESIM's adaptive sampling, made per pixel): a step
whose change of the pixel's ``L = ln(I + ε)`` exceeds ``max_dlog`` (half the contrast) is shortened
until it does not or is ``min_dt_us`` long, and the next step grows or shrinks with the change of
this one, up to ``max_dt_us`` (8° of the turn), and around the intervals of the shadow grid in
which a cast shadow falls on the pixel while it is lit, up to one interval, so no sweep is stepped
over; L may also leave the previous step's line by at most ``MAX_BEND``. ``I`` is the area average of the frame
pixels under the event pixel, each shaded in closed form at the step's time; crossings are placed
exactly on the line between samples, by either refractory rule of ``pstoolkit.events.rule``
("reset-at-end": ``_fire_lanes``; "rate-limited": ``_fire_lanes_paced``, R > 0). Each frame pixel
belongs to the event pixel covering most of it, and its ∫ V·[n·l]₊ dt and ∫ V·[n·l]₊·ratio dt
(``ratio`` the GGX specular factor) accumulate by the trapezoid rule on that pixel's samples, in
its slot of the owner's footprint: the exposures come from the same shading as the events.

Work per event pixel is about (number of steps) × (frame pixels under it): a pixel that sees no
change takes ``max_dt_us`` steps, one that fires takes about three steps per event. A thread steps
``LANES`` pixels at once, each lane's state at its index of arrays across the lanes, so shading, log,
step control and firing rule run as SIMD loops (``_shade_lanes``, ``_log_lanes``: a series for ln,
``_fire_lanes``, and the light's azimuth turned on from the lane's last sample by a series for cos
and sin, ``_turn``); a lane takes its pixel's frame-pixel constants (``_load_lane``) and sums
((E, K, 2), one per slot of its footprint) and gives the sums back when the pixel is done. Memory:
the per-pixel state, a cast-shadow table for the current block of time, and the block's events
(room for ``FIRST_ROOM`` per pixel at first, within ``ROOM_BYTES``, then for as many as the busiest
pixel needed so far; pixels that overflow it are run again from their state at the block's start).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import numba
import numpy as np
import torch
from numba.cpython.unsafe.numbers import trailing_zeros

from psfmt import EventArray
from pstoolkit._shared.worksharing import take_task
from pstoolkit.errors import UserError
from pstoolkit.events.rule import GREY_WEIGHTS, LOG_EPS, REFRACTORY_RULE, REFRACTORY_RULES, check_rule
from pstoolkit.grid import event_shape
from pstoolkit.optics.brdf import GGX, HALF_EPS
from pstoolkit.optics.lights import US_PER_S, RingLight
from pstoolkit.sim.esim import check_options, draw_thresholds, event_rngs
from pstoolkit.sim.render import Renderer

# Columns of the per-frame-pixel constants (``FrameConstants.values``).
NX, NY, NZ, GREY_DIFFUSE, GREY_SPECULAR, NORM2, ALPHA2_1, K, ONE_K, VIEW = range(10)
# Longest step, as a share of the light's turn, away from the shadow-grid intervals in which a cast shadow falls on
# the pixel while it is lit (around those a pixel steps at most one interval, so no sweep is stepped over).
MAX_STEP_TURNS = 8.0 / 360.0
# Largest distance of L from the line of a pixel's previous step at the end of the next one: the line
# between the step's samples is then within about a quarter of it (1e-3) of L, so events keep the
# threshold rule where L curves (a highlight) even when its change over the step is small.
MAX_BEND = 4e-3
# Event pixels handed to a thread at a time: pixels differ a lot in work (a dark background pixel
# against one a shadow edge sweeps), so threads take chunks as they finish instead of equal shares;
# a chunk is long enough that its lanes are seldom idle (a task's last pixels leave lanes without
# work): 1024 took 5–10 % less time than 256 and as long as 512 or 2048 (256×256 blobs and sphere,
# refractory 0).
PIXELS_PER_TASK = 1024
# Pixels a task steps at once (see ``_advance_pixels``): 32 lanes took 20 % less time than 16, 10 %
# less than 64 (256×256 blobs, one thread).
LANES = 32
# Length of a block of time, in shadow-grid intervals: one shadow table and one batch of events. Each
# block ends with a sample of every pixel and costs a table, masks and an event sort: 60 took 7–9 %
# less time than 32 (256×256 blobs and sphere, refractory 0).
BLOCK_GRID_STEPS = 60
# Most grid times in a block's shadow table: one bit each in ``_lit_shadow``'s masks. A block of n
# intervals that starts between grid times spans up to n + 3 of them, so a block is at most
# ``TABLE_ROWS`` − 3 intervals long (a window's short last stretch joins the block before only within it).
TABLE_ROWS = 64
# Columns of the shadow table whose masks ``_lit_shadow`` builds at once: their 8 KiB of bits stay in
# the L1 cache while the table's rows stream by.
SHADOW_TILE = 1024
# First room for events per pixel and block, and the most memory (bytes) it may take at first: a pixel
# that fires more is run again, which cost 5–6 % more renders with room for 8 (256×256 sphere and
# blobs at refractory 0) and, with 64, a widening of the room (a copy) in each blobs capture, whose
# busiest pixels fire 75–84 times a block at refractory 0 (the sphere's 34–56).
FIRST_ROOM = 128
ROOM_BYTES = 32 << 20
# Runs of pixels the event sort of a block counts and places in parallel (see ``_gather``); fixed, so
# the work does not depend on the threads.
GATHER_RUNS = 16


@dataclass
class FrameConstants:
    """Per masked frame pixel, what the closed form needs (``values`` (P, 10) float64, columns named
    above): normal, grey of e·albedo and of e·F0, |n|², α² − 1, k, 1 − k and α²/(4π G1-denominator of
    n·v); ``specular`` False for a Lambertian scene (the GGX columns unused)."""

    values: np.ndarray
    specular: bool


@dataclass
class Footprints:
    """Which masked frame pixels each event pixel averages: ``pixel`` (E, K) positions into the masked
    frame pixels (−1 for an unused slot), ``weight`` (E, K) area weights, ``owned`` (E, K) whether this
    event pixel integrates that frame pixel's exposure (each frame pixel has exactly one owner)."""

    pixel: np.ndarray
    weight: np.ndarray
    owned: np.ndarray


@dataclass
class PixelState:
    """Where each event pixel stands at the start of a block (all at the same time): its level ``level``
    (L at that time), firing levels ``hi``/``lo`` and ``blind_until_us`` — for "reset-at-end" ±inf
    while blind and inf unless a reset is pending, for "rate-limited" always the reference ± C and
    the end of the blind time (−inf before the first event) —, next step ``step_us``, slope of L over
    the last step ``slope`` (per µs, NaN before the first); and per slot of its footprint (the frame pixels under it, see
    ``Footprints``) the last V·[n·l]₊ and V·[n·l]₊·ratio (``shade``, (E, K, 2)) and the exposure
    sums of the current window (``sums``, (E, K, 2), µs)."""

    level: np.ndarray
    hi: np.ndarray
    lo: np.ndarray
    blind_until_us: np.ndarray
    step_us: np.ndarray
    slope: np.ndarray
    shade: np.ndarray
    sums: np.ndarray


# Direction of the ring light: a lane turns it from the azimuth at its last sample by the step's angle
# (at most ``MAX_STEP_TURNS`` of the turn, 0.14 rad) with the series of cos and sin, whose first
# omitted terms are below 1e-18: cheaper than the library's cos and sin, and SIMD.
@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _turn(d: float) -> tuple[float, float]:  # pragma: no cover - compiled
    """cos d and sin d for |d| ≤ 0.2 (to 1e-17)."""
    d2 = d * d
    c = 1.0 / 40320.0 - d2 * (1.0 / 3628800.0)
    c = 1.0 / 720.0 - d2 * c
    c = 1.0 / 24.0 - d2 * c
    c = 0.5 - d2 * c
    s = 1.0 / 362880.0 - d2 * (1.0 / 39916800.0)
    s = 1.0 / 5040.0 - d2 * s
    s = 1.0 / 120.0 - d2 * s
    s = 1.0 / 6.0 - d2 * s
    return 1.0 - d2 * c, d * (1.0 - d2 * s)


_LN2 = math.log(2.0)
_SQRT2 = math.sqrt(2.0)
_MANTISSA = 0x000FFFFFFFFFFFFF
_ONE_BITS = 0x3FF0000000000000


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _log_lanes(
    x: np.ndarray, out: np.ndarray, exponent: np.ndarray, mantissa: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """``out`` = ln ``x`` for positive normal ``x`` (to about 1 ulp), in SIMD: x = 2^e·m with m in
    [√½, √2), ln m = 2 atanh((m − 1)/(m + 1)) by its series to the 21st power (|z| ≤ 0.172, the first
    omitted term below 1e-18). ``exponent`` and ``mantissa`` are (W,) int64 scratch."""
    bits = x.view(np.int64)
    m_float = mantissa.view(np.float64)
    for k in range(x.size):
        exponent[k] = (bits[k] >> 52) - 1023
        mantissa[k] = (bits[k] & _MANTISSA) | _ONE_BITS
    for k in range(x.size):
        m = m_float[k]
        big = m > _SQRT2
        m = 0.5 * m if big else m
        e = exponent[k] + 1 if big else exponent[k]
        z = (m - 1.0) / (m + 1.0)
        z2 = z * z
        p = 1.0 / 21.0
        p = p * z2 + 1.0 / 19.0
        p = p * z2 + 1.0 / 17.0
        p = p * z2 + 1.0 / 15.0
        p = p * z2 + 1.0 / 13.0
        p = p * z2 + 1.0 / 11.0
        p = p * z2 + 1.0 / 9.0
        p = p * z2 + 1.0 / 7.0
        p = p * z2 + 1.0 / 5.0
        p = p * z2 + 1.0 / 3.0
        p = p * z2 + 1.0
        out[k] = e * _LN2 + 2.0 * z * p


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _shade_lanes(
    t1: np.ndarray, cos_az: np.ndarray, sin_az: np.ndarray, consts: np.ndarray, frame: np.ndarray,
    frame_t: np.ndarray, shadows: np.ndarray, specular: bool, ring: tuple, openness: np.ndarray,
    column_major: np.ndarray, grid: tuple, eps: float, now: np.ndarray, grey: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """Grey irradiance + ``eps`` of each lane's event pixel at its time ``t1`` into ``grey`` (W,),
    the light at azimuth (``cos_az``, ``sin_az``); ``now`` (2, K, W) gets each slot's V·[n·l]₊ and
    V·[n·l]₊·ratio (``consts`` (10, K, W), ``frame`` and ``frame_t`` (K, W): the lanes' slots'
    constants and flat frame positions row- and column-major, the columns of ``openness``'s rows
    without and with ``column_major``, see ``_load_lane``). V is read only where a lane's
    ``shadows`` (W,) has the bit of the table interval of its time (``_lit_shadow``'s bits of its
    frame pixels): elsewhere V ≥ 1 at both ends of the interval, or the pixels face away from the
    light through it, and V changes nothing. The loops run across the lanes, so they compile to SIMD."""
    cos_e, sin_e, inv_h, hh, lift = ring[0], ring[1], ring[5], ring[6], ring[7]
    hz = 1.0 + sin_e
    lanes, taps = t1.size, consts.shape[1]
    for k in range(lanes):
        grey[k] = eps
    for q in range(taps):
        for k in range(lanes):
            across = cos_e * (consts[NX, q, k] * cos_az[k] + consts[NY, q, k] * sin_az[k])
            nl = across + consts[NZ, q, k] * sin_e
            nh = (across + consts[NZ, q, k] * hz) * inv_h
            d = nh * nh * consts[ALPHA2_1, q, k] + lift + hh * consts[NORM2, q, k]
            ratio = consts[VIEW, q, k] / (d * d * (consts[K, q, k] + nl * consts[ONE_K, q, k]))
            lit = nl > 0.0
            now[0, q, k] = nl if lit else 0.0
            now[1, q, k] = ratio if lit and specular else 0.0
    rows = openness.shape[0]
    for k in range(lanes):
        if shadows[k] == 0:
            continue
        x = t1[k] / grid[0] - grid[1]
        row = min(max(int(math.floor(x)), 0), rows - 2)
        if not (shadows[k] >> np.uint64(row)) & np.uint64(1):
            continue
        after = x - row
        major, major_next = column_major[row], column_major[row + 1]
        for q in range(taps):
            f, f_t = frame[q, k], frame_t[q, k]
            v = openness[row, f_t if major else f] * (1.0 - after) + openness[row + 1, f_t if major_next else f] * after
            now[0, q, k] *= min(max(v, 0.0), 1.0)
    for q in range(taps):
        for k in range(lanes):
            nl, ratio = now[0, q, k], now[1, q, k]
            grey[k] += nl * (consts[GREY_DIFFUSE, q, k] + ratio * consts[GREY_SPECULAR, q, k])
            now[1, q, k] = nl * ratio


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _idle_slot(
    consts: np.ndarray, frame: np.ndarray, frame_t: np.ndarray, q: int, k: int,
) -> None:  # pragma: no cover - compiled
    """Slot ``q`` of lane ``k`` without a frame pixel: constants of zero (no light), but |n|² and k of
    one, which keep its shading finite, at frame position 0."""
    for col in range(consts.shape[0]):
        consts[col, q, k] = 0.0
    consts[NORM2, q, k] = 1.0
    consts[K, q, k] = 1.0
    frame[q, k] = 0
    frame_t[q, k] = 0


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _idle_lanes(columns: int, taps: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """(10, K, LANES) constants and two (K, LANES) frame positions (row- and column-major) of lanes
    without a pixel (``_idle_slot``)."""
    consts, frame, frame_t = np.empty((columns, taps, LANES)), np.empty((taps, LANES), np.int64), np.empty((taps, LANES), np.int64)
    for q in range(taps):
        for k in range(LANES):
            _idle_slot(consts, frame, frame_t, q, k)
    return consts, frame, frame_t


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _load_lane(
    consts: np.ndarray, frame: np.ndarray, frame_t: np.ndarray, k: int, p: int, values: np.ndarray,
    weight: np.ndarray, pixel: np.ndarray, index: np.ndarray, index_t: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """Lane ``k`` takes event pixel ``p``: per slot of its footprint (``Footprints``), the frame
    pixel's ``FrameConstants.values`` with the greys times the slot's area weight, and its flat
    positions row- and column-major (``index``, ``index_t``); an unused slot is idle (``_idle_slot``:
    adds nothing)."""
    for q in range(pixel.shape[1]):
        f = pixel[p, q]
        if f < 0:
            _idle_slot(consts, frame, frame_t, q, k)
            continue
        for col in range(values.shape[1]):
            consts[col, q, k] = values[f, col]
        consts[GREY_DIFFUSE, q, k] *= weight[p, q]
        consts[GREY_SPECULAR, q, k] *= weight[p, q]
        frame[q, k] = index[f]
        frame_t[q, k] = index_t[f]


# Rows of ``_fire_lanes``' output per lane: events, level of the first, level between them, the line's
# start level and 1/rise (all in the events' sense), and the sense (±1).
FIRE_COUNT, FIRE_FIRST, FIRE_GAP, FIRE_FROM, FIRE_INV_SPAN, FIRE_SIGN = range(6)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _fire_lanes(
    accepted: np.ndarray, ta: np.ndarray, la: np.ndarray, tb: np.ndarray, lb: np.ndarray, c_pos: np.ndarray,
    c_neg: np.ndarray, refractory_us: float, hi: np.ndarray, lo: np.ndarray, blind_until: np.ndarray,
    fire: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """The events of each ``accepted`` lane on the line from (``ta``, ``la``) to (``tb``, ``lb``) by
    the rule of ``pstoolkit.events.rule`` (as ``esim._Pixels`` applies it to whole sensors): its firing
    state ``hi``, ``lo``, ``blind_until`` updated, and in ``fire`` (6, W) what ``_emit`` needs to
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
def _emit(
    fire: np.ndarray, k: int, ta: float, tb: float, out_t: np.ndarray, out_p: np.ndarray, n: int,
) -> int:  # pragma: no cover - compiled
    """Lane ``k``'s events from ``_fire_lanes`` on its step from ``ta`` to ``tb``, stored in the rows
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


# Rows of ``_fire_lanes_paced``' output per lane, for each of its two runs (``PACED_ROWS`` apart):
# events, the first time the pixel may fire, the crossing of the first threshold, the time between
# thresholds on the line, and the sign; the k-th event (from 0) of a run is at
# max(start + k·R, crossing + k·spacing).
PACED_COUNT, PACED_START, PACED_CROSSING, PACED_SPACING, PACED_SIGN = range(5)
PACED_ROWS = 5


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _fire_lanes_paced(
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
def _emit_paced(
    fire: np.ndarray, k: int, refractory_us: float, out_t: np.ndarray, out_p: np.ndarray, n: int,
) -> int:  # pragma: no cover - compiled
    """Lane ``k``'s events from ``_fire_lanes_paced``, its two runs in order, stored in the rows
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


_TINY = np.finfo(np.float64).tiny


@numba.njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def _lit_shadow(
    values: np.ndarray, index: np.ndarray, index_t: np.ndarray, sin_e: float, openness: np.ndarray,
    column_major: np.ndarray, grid_light: np.ndarray,
) -> np.ndarray:  # pragma: no cover - compiled
    """(H·W,) uint64: bit i set where a cast shadow falls on the frame pixel while it is lit between
    grid times i and i + 1 of the table (V < 1 at one of them, next to a grid time where n·l > 0: a
    shadow inside the attached shadow changes nothing, as on the far side of a sphere); at most
    ``TABLE_ROWS`` grid times. ``grid_light`` (3, rows): the light's x and y at each grid time of
    the table and how far n·l may exceed its values at the grid times around (n·l is a sinusoid in
    the azimuth). ``values`` are the masked pixels' ``FrameConstants``, ``index`` and ``index_t``
    their flat positions row- and column-major, the columns of ``openness``'s rows without and with
    ``column_major`` (``Renderer.frame_openness``)."""
    rows, span = openness.shape
    if rows > TABLE_ROWS:
        raise ValueError("_lit_shadow: a shadow table of more than TABLE_ROWS grid times")
    pixels = index.size
    # bit r: V < 1 at grid time r, by column of the row-major rows and of the column-major ones; in
    # tiles of columns whose bits stay in the L1 cache while the table's rows stream by (SIMD)
    below = np.empty(span, np.uint64)
    below_t = np.empty(span, np.uint64)
    for tile in numba.prange((span + SHADOW_TILE - 1) // SHADOW_TILE):
        start, stop = tile * SHADOW_TILE, min((tile + 1) * SHADOW_TILE, span)
        bits, bits_t = below[start:stop], below_t[start:stop]
        bits[:] = 0
        bits_t[:] = 0
        for row in range(rows):
            line, target = openness[row, start:stop], bits_t if column_major[row] else bits
            bit = np.uint64(1) << np.uint64(row)
            for j in range(stop - start):
                target[j] |= bit if line[j] < 1.0 else np.uint64(0)
    out = np.zeros(span, np.uint64)
    light_x, light_y, slack = grid_light[0], grid_light[1], grid_light[2]
    intervals = (np.uint64(1) << np.uint64(rows - 1)) - np.uint64(1)
    # most pixels are never shadowed in a block and are done with at the first test
    for run in numba.prange((pixels + PIXELS_PER_TASK - 1) // PIXELS_PER_TASK):
        for f in range(run * PIXELS_PER_TASK, min((run + 1) * PIXELS_PER_TASK, pixels)):
            shadow = below[index[f]] | below_t[index_t[f]]
            if shadow == 0:
                continue
            lit = np.uint64(0)
            for row in range(rows):
                nl = values[f, NX] * light_x[row] + values[f, NY] * light_y[row] + values[f, NZ] * sin_e
                lit |= (np.uint64(1) << np.uint64(row)) if nl > -slack[row] else np.uint64(0)
            # the light first: on a sphere's far side the whole table is below one but nothing is lit
            near = shadow & (lit | (lit << np.uint64(1)) | (lit >> np.uint64(1)))
            out[index[f]] = (near | (near >> np.uint64(1))) & intervals
    return out


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _shadow_room(
    t_us: float, shadows: np.uint64, grid: tuple, grid_dt: float, max_dt: float,
) -> float:  # pragma: no cover - compiled
    """Longest step from ``t_us`` of a pixel whose frame pixels are shadowed while lit in the grid
    intervals ``shadows`` (bits, see ``_lit_shadow``): one grid interval inside such an interval or
    close to one, else up to the next one (no sweep is stepped over), at most ``max_dt``."""
    if shadows == 0:
        return max_dt
    i = min(max(int(math.floor(t_us / grid[0] - grid[1])), 0), 63)
    rest = shadows >> np.uint64(i)
    if rest & np.uint64(1):
        return grid_dt
    rest >>= np.uint64(1)
    if rest == 0:
        return max_dt
    j = i + 1 + int(trailing_zeros(rest))
    return min(max((grid[1] + j) * grid[0] - t_us, grid_dt), max_dt)


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _next_try(h: float, left: float, min_dt: float) -> float:  # pragma: no cover - compiled
    """The step to try next: ``h``, or all that is ``left`` of the block when ``h`` reaches it or
    would leave less than ``min_dt`` of it."""
    return left if (h >= left or left - h < min_dt) else h


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _advance_pixels(
    order: np.ndarray, first: int, last: int, ta: float, tb: float, values: np.ndarray, weight: np.ndarray,
    pixel: np.ndarray, index: np.ndarray, index_t: np.ndarray, specular: bool, ring: tuple, openness: np.ndarray,
    column_major: np.ndarray, grid: tuple, reach: np.ndarray, c_pos: np.ndarray, c_neg: np.ndarray,
    refractory_us: float, paced: bool, eps: float, max_dlog: float, min_dt: float, max_dt: float, grid_dt: float,
    level: np.ndarray, hi: np.ndarray, lo: np.ndarray, blind_until: np.ndarray, step: np.ndarray, slope: np.ndarray,
    shade: np.ndarray, sums: np.ndarray, out_t: np.ndarray, out_p: np.ndarray, count: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """Event pixels ``order[first:last]`` from ``ta`` to ``tb``, ``LANES`` at a time: each lane
    steps its own pixel, and a lane's state sits at its index of arrays across the lanes, so the
    shading, the log, the step control and the firing rule of all lanes run as SIMD loops; only the
    lanes that store events, finish or have cast shadows near take scalar turns. The firing rule
    is "rate-limited" when ``paced`` (``_fire_lanes_paced``), else "reset-at-end" (``_fire_lanes``)."""
    taps = pixel.shape[1]
    w = LANES
    omega, t0, phase = ring[3], ring[4], ring[2]
    cos_a, sin_a = math.cos(phase + omega * (ta - t0)), math.sin(phase + omega * (ta - t0))
    lane = np.zeros(w, np.int64)
    active = np.zeros(w, np.bool_)
    # a lane's pixel state (as ``PixelState``) and the azimuth at its last sample
    t, l0, s0, h, h_try = np.full(w, tb), np.zeros(w), np.zeros(w), np.zeros(w), np.ones(w)
    l_hi, l_lo, l_blind, l_pos, l_neg = np.zeros(w), np.zeros(w), np.zeros(w), np.zeros(w), np.zeros(w)
    n = np.zeros(w, np.int64)
    shadows = np.zeros(w, np.uint64)
    cos_az, sin_az = np.ones(w), np.zeros(w)
    consts, frame, frame_t = _idle_lanes(values.shape[1], taps)
    last_shade, l_sums = np.zeros((2, taps, w)), np.zeros((2, taps, w))
    # the trial sample
    t1, cos1, sin1, l1, grey = np.empty(w), np.empty(w), np.empty(w), np.empty(w), np.empty(w)
    now = np.zeros((2, taps, w))
    exponent, mantissa = np.empty(w, np.int64), np.empty(w, np.int64)
    dt, grown = np.empty(w), np.empty(w)
    accepted, fire = np.zeros(w, np.bool_), np.zeros((2 * PACED_ROWS, w))
    taken = first
    while True:
        # idle lanes take the next pixels with frame pixels (those without fire nothing)
        for k in range(w):
            if active[k]:
                continue
            while taken < last and pixel[order[taken], 0] < 0:
                count[order[taken]] = 0
                taken += 1
            if taken == last:
                continue
            p = order[taken]
            taken += 1
            lane[k], active[k] = p, True
            _load_lane(consts, frame, frame_t, k, p, values, weight, pixel, index, index_t)
            # a pixel on which no cast shadow falls while lit during the block skips the table, and
            # one whose shadows come and go steps short only around them
            shadows[k] = 0
            for q in range(taps):
                if pixel[p, q] >= 0:
                    shadows[k] |= reach[frame[q, k]]
                for j in range(2):
                    last_shade[j, q, k] = shade[p, q, j]
                    l_sums[j, q, k] = sums[p, q, j]
            t[k], l0[k], s0[k], n[k] = ta, level[p], slope[p], 0
            l_hi[k], l_lo[k], l_blind[k], l_pos[k], l_neg[k] = hi[p], lo[p], blind_until[p], c_pos[p], c_neg[p]
            cos_az[k], sin_az[k] = cos_a, sin_a
            h[k] = min(step[p], _shadow_room(ta, shadows[k], grid, grid_dt, max_dt))
            h_try[k] = _next_try(h[k], tb - ta, min_dt)
        if not active.any():
            break
        # the trial samples: time, azimuth turned on from the last sample, shading, log
        for k in range(w):
            t1[k] = tb if h_try[k] >= tb - t[k] else t[k] + h_try[k]
            cos_d, sin_d = _turn(omega * (t1[k] - t[k]))
            cos1[k] = cos_az[k] * cos_d - sin_az[k] * sin_d
            sin1[k] = sin_az[k] * cos_d + cos_az[k] * sin_d
        _shade_lanes(t1, cos1, sin1, consts, frame, frame_t, shadows, specular, ring, openness, column_major, grid, eps,
                     now, grey)
        _log_lanes(grey, l1, exponent, mantissa)
        # step control: a step whose change or bend is too large is shortened and tried again
        for k in range(w):
            dt[k] = t1[k] - t[k]
            change = abs(l1[k] - l0[k])
            # how far L left the line of the previous step: 4× the error of the line between samples
            bend = abs(l1[k] - l0[k] - s0[k] * dt[k])
            bend = 0.0 if s0[k] != s0[k] else bend
            rejected = h_try[k] > min_dt and (change > max_dlog or bend > MAX_BEND)
            shrink = min(0.9 * max_dlog / max(change, max_dlog), math.sqrt(0.9 * MAX_BEND / max(bend, MAX_BEND)))
            grow = min(2.0, 0.8 * max_dlog / max(change, 1e-12), math.sqrt(0.8 * MAX_BEND / max(bend, 1e-12)))
            grown[k] = max(min_dt, h_try[k] * max(0.5, grow))
            h_try[k] = max(min_dt, h_try[k] * max(0.2, shrink)) if rejected else h_try[k]
            accepted[k] = active[k] and not rejected
        # events: the firing rule in SIMD, then each firing lane's events stored
        if paced:
            _fire_lanes_paced(accepted, t, l0, t1, l1, l_pos, l_neg, refractory_us, l_hi, l_lo, l_blind, fire)
            for k in range(w):
                if fire[PACED_COUNT, k] > 0 or fire[PACED_ROWS + PACED_COUNT, k] > 0:
                    p = lane[k]
                    n[k] = _emit_paced(fire, k, refractory_us, out_t[p], out_p[p], n[k])
        else:
            _fire_lanes(accepted, t, l0, t1, l1, l_pos, l_neg, refractory_us, l_hi, l_lo, l_blind, fire)
            for k in range(w):
                if fire[FIRE_COUNT, k] > 0:
                    p = lane[k]
                    n[k] = _emit(fire, k, t[k], t1[k], out_t[p], out_p[p], n[k])
        # accepted samples: exposure sums by the trapezoid rule, the next step
        for q in range(taps):
            for k in range(w):
                for j in range(2):
                    add = 0.5 * (last_shade[j, q, k] + now[j, q, k]) * dt[k]
                    l_sums[j, q, k] += add if accepted[k] else 0.0
                    last_shade[j, q, k] = now[j, q, k] if accepted[k] else last_shade[j, q, k]
        for k in range(w):
            a = accepted[k]
            h[k] = min(max_dt, grown[k]) if a else h[k]
            s0[k] = (l1[k] - l0[k]) / dt[k] if a else s0[k]
            t[k] = t1[k] if a else t[k]
            l0[k] = l1[k] if a else l0[k]
            cos_az[k] = cos1[k] if a else cos_az[k]
            sin_az[k] = sin1[k] if a else sin_az[k]
            h_try[k] = _next_try(h[k], tb - t[k], min_dt) if a else h_try[k]
        for k in range(w):
            if not accepted[k]:
                continue
            if shadows[k]:
                h[k] = min(_shadow_room(t[k], shadows[k], grid, grid_dt, max_dt), grown[k])
                h_try[k] = _next_try(h[k], tb - t[k], min_dt)
            if t[k] < tb:
                continue
            p = lane[k]
            count[p] = n[k]
            active[k] = False
            # a pixel that fired more than it had room for keeps its state of the block's start: it is run again
            if n[k] > out_t.shape[1]:
                continue
            level[p], step[p], slope[p] = l0[k], h[k], s0[k]
            hi[p], lo[p], blind_until[p] = l_hi[k], l_lo[k], l_blind[k]
            for q in range(taps):
                for j in range(2):
                    shade[p, q, j] = last_shade[j, q, k]
                    sums[p, q, j] = l_sums[j, q, k]


@numba.njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def _advance(
    order: np.ndarray, ta: float, tb: float, values: np.ndarray, weight: np.ndarray, pixel: np.ndarray,
    index: np.ndarray, index_t: np.ndarray, specular: bool, ring: tuple, openness: np.ndarray,
    column_major: np.ndarray, grid: tuple, reach: np.ndarray, c_pos: np.ndarray, c_neg: np.ndarray,
    refractory_us: float, paced: bool, eps: float, max_dlog: float, min_dt: float, max_dt: float, grid_dt: float,
    level: np.ndarray, hi: np.ndarray, lo: np.ndarray, blind_until: np.ndarray,
    step: np.ndarray, slope: np.ndarray, shade: np.ndarray, sums: np.ndarray, out_t: np.ndarray, out_p: np.ndarray,
    count: np.ndarray, threads: int,
) -> None:  # pragma: no cover - compiled
    """The event pixels ``order`` from ``ta`` to ``tb`` (see the module docstring), ``PIXELS_PER_TASK``
    to a task, each of the ``threads`` (numba's) taking the next task as it comes free
    (``pstoolkit._shared.worksharing``); state arrays are updated in place, events go to ``out_t``/``out_p``
    and their numbers to ``count``."""
    tasks = (order.shape[0] + PIXELS_PER_TASK - 1) // PIXELS_PER_TASK
    # set, not np.zeros: under parallel=True that would be a parallel loop of its own
    taken = np.empty(1, np.int64)
    taken[0] = 0
    for _ in numba.prange(threads):
        while True:
            task = take_task(taken)
            if task >= tasks:
                break
            first = task * PIXELS_PER_TASK
            _advance_pixels(order, first, min(first + PIXELS_PER_TASK, order.shape[0]), ta, tb, values, weight, pixel,
                            index, index_t, specular, ring, openness, column_major, grid, reach, c_pos, c_neg,
                            refractory_us, paced, eps, max_dlog, min_dt, max_dt, grid_dt, level, hi, lo, blind_until, step,
                            slope, shade, sums, out_t, out_p, count)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _start(
    t_us: float, values: np.ndarray, weight: np.ndarray, pixel: np.ndarray, index: np.ndarray, index_t: np.ndarray,
    specular: bool, ring: tuple, openness: np.ndarray, column_major: np.ndarray, grid: tuple, shadows: bool,
    eps: float, level: np.ndarray, shade: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """Levels and slot shading at ``t_us`` (the start of the simulation), ``LANES`` pixels at a time
    as ``_advance_pixels`` shades them."""
    taps = pixel.shape[1]
    consts, frame, frame_t = _idle_lanes(values.shape[1], taps)
    azimuth = ring[2] + ring[3] * (t_us - ring[4])
    t1, cos_az, sin_az = np.full(LANES, t_us), np.full(LANES, math.cos(azimuth)), np.full(LANES, math.sin(azimuth))
    # every interval, or none without cast shadows
    every = np.full(LANES, np.uint64(0xFFFFFFFFFFFFFFFF) if shadows else np.uint64(0))
    now, grey, l1 = np.zeros((2, taps, LANES)), np.empty(LANES), np.empty(LANES)
    exponent, mantissa = np.empty(LANES, np.int64), np.empty(LANES, np.int64)
    for first in range(0, pixel.shape[0], LANES):
        used = min(LANES, pixel.shape[0] - first)
        for k in range(used):
            _load_lane(consts, frame, frame_t, k, first + k, values, weight, pixel, index, index_t)
        _shade_lanes(t1, cos_az, sin_az, consts, frame, frame_t, every, specular, ring, openness, column_major, grid,
                     eps, now, grey)
        _log_lanes(grey, l1, exponent, mantissa)
        for k in range(used):
            level[first + k] = l1[k]
            for q in range(taps):
                for j in range(2):
                    shade[first + k, q, j] = now[j, q, k]


@numba.njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def _gather(out_t: np.ndarray, out_p: np.ndarray, count: np.ndarray, width: int, t_first: int, t_last: int,
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """The events of a block, at whole µs in [``t_first``, ``t_last``], sorted by (µs, pixel): a
    counting sort on the µs, in parallel over ``GATHER_RUNS`` runs of pixels. Slots are laid out µs
    by µs and, within one, run by run; each run visits its pixels in order, each pixel's events in
    time order, so ties keep pixel order and, within a pixel, emission order."""
    pixels = count.shape[0]
    total = 0
    for p in range(pixels):
        total += count[p]
    x = np.empty(total, np.uint16)
    y = np.empty(total, np.uint16)
    t_out = np.empty(total, np.int64)
    p_out = np.empty(total, np.int8)
    span = t_last - t_first + 1
    run_pixels = (pixels + GATHER_RUNS - 1) // GATHER_RUNS
    slots = np.zeros((GATHER_RUNS, span), np.int64)
    for run in numba.prange(GATHER_RUNS):
        mine = slots[run]
        for p in range(run * run_pixels, min((run + 1) * run_pixels, pixels)):
            for i in range(count[p]):
                mine[out_t[p, i] - t_first] += 1
    at = 0
    for k in range(span):
        for run in range(GATHER_RUNS):
            n = slots[run, k]
            slots[run, k] = at
            at += n
    for run in numba.prange(GATHER_RUNS):
        mine = slots[run]
        for p in range(run * run_pixels, min((run + 1) * run_pixels, pixels)):
            column, row = p % width, p // width
            for i in range(count[p]):
                t = out_t[p, i]
                j = mine[t - t_first]
                mine[t - t_first] += 1
                x[j] = column
                y[j] = row
                t_out[j] = t
                p_out[j] = out_p[p, i]
    return x, y, t_out, p_out


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _exposure_images(
    sums: np.ndarray, albedo: np.ndarray, f0: np.ndarray, e_per_us: np.ndarray, index: np.ndarray, out: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """Into ``out`` (2, H·W, 3), zero outside the masked pixels ``index``: albedo·e·∫ V·[n·l]₊ dt, then that
    plus F0·e·∫ V·[n·l]₊·ratio dt (``sums`` (P, 2), dt in µs; ``e_per_us`` the RGB intensity per µs)."""
    for i in range(index.size):
        f = index[i]
        for c in range(3):
            diffuse = albedo[i, c] * sums[i, 0] * e_per_us[c]
            out[0, f, c] = diffuse
            out[1, f, c] = diffuse + f0[i, c] * sums[i, 1] * e_per_us[c]


def window_exposures(renderer: Renderer, sums: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The (H, W, 3) float64 radiant exposures (dt in seconds) of a window from its ``Block.window_sums``:
    the diffuse part alone, and with the GGX specular part (as ``renderer`` shades them)."""
    rgb = renderer.closed_form_constants()[1]
    e_per_us = np.asarray(renderer.light.intensity, dtype=np.float64) / US_PER_S  # type: ignore[attr-defined]
    out = np.zeros((2, renderer.maps.height * renderer.maps.width, 3))
    _exposure_images(sums, rgb["albedo"].cpu().numpy(), rgb["f0"].cpu().numpy(), e_per_us, renderer.index, out)
    diffuse, gloss = out.reshape(2, renderer.maps.height, renderer.maps.width, 3)
    return diffuse, gloss


@dataclass
class Block:
    """What one block of time produced: its events (sorted by µs, then pixel), its end, and — when a
    window of ``window_ends_us`` ends with it — that window's (P, 2) sums ∫ V·[n·l]₊ dt and
    ∫ V·[n·l]₊·ratio dt per masked frame pixel (dt in µs)."""

    events: EventArray
    t_end_us: float
    window_sums: np.ndarray | None


def supported(renderer: Renderer) -> bool:
    """Whether ``simulate_ring`` can render this renderer's scene: a ring light, the ``ggx`` or
    ``lambertian`` BRDF in closed form, on the CPU, with cast shadows on a shadow grid (or none)."""
    return (
        isinstance(renderer.light, RingLight)
        and renderer.event_pixels_supported
        and renderer.device.type == "cpu"
    )


def frame_constants(renderer: Renderer) -> FrameConstants:
    """The closed form's per-pixel constants of ``renderer`` (its own, so the kernel shades as it does)."""
    c, rgb = renderer.closed_form_constants()
    e_grey = np.asarray(renderer.light.intensity, dtype=np.float64) * np.asarray(GREY_WEIGHTS)  # type: ignore[attr-defined]
    columns = {
        NX: c["nT"][0], NY: c["nT"][1], NZ: c["nT"][2],
        GREY_DIFFUSE: rgb["albedo"] @ torch.as_tensor(e_grey, dtype=torch.float64),
        GREY_SPECULAR: rgb["f0"] @ torch.as_tensor(e_grey, dtype=torch.float64),
        NORM2: c["nn"], ALPHA2_1: c["alpha2_1"], K: c["k"], ONE_K: c["1_k"], VIEW: c["dv"],
    }
    values = np.stack([columns[i].cpu().numpy() for i in range(len(columns))], axis=1)
    return FrameConstants(np.ascontiguousarray(values), isinstance(renderer.brdf, GGX))


def footprints(renderer: Renderer, event_scale: float) -> Footprints:
    """The event pixels' frame pixels (``Renderer.footprint``), unused slots last and marked −1, and
    each frame pixel's owner: the event pixel covering most of it (the first such on a tie)."""
    position, weight = (np.ascontiguousarray(a.cpu().numpy()) for a in renderer.footprint(event_scale))
    pixel, ordered, owned = np.empty_like(position), np.empty_like(weight), np.zeros(position.shape, np.bool_)
    _order_slots(position, weight, renderer.pixels, pixel, ordered, owned)
    return Footprints(pixel, ordered, owned)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _order_slots(
    position: np.ndarray, weight: np.ndarray, pixels: int, pixel: np.ndarray, ordered: np.ndarray, owned: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """``footprints`` in one pass over the (E, K) slots: each event pixel's used slots (weight > 0)
    first, in their order, then the unused (position −1); the slot with a frame pixel's largest
    weight owns it, the first in flat order on a tie."""
    best = np.full(pixels, -np.inf)
    owner = np.full(pixels, -1, np.int64)
    taps = position.shape[1]
    for e in range(position.shape[0]):
        j = 0
        for used in (True, False):
            for q in range(taps):
                if (weight[e, q] > 0) == used:
                    pixel[e, j] = position[e, q] if used else -1
                    ordered[e, j] = weight[e, q]
                    j += 1
        for q in range(taps):
            f = pixel[e, q]
            if f >= 0 and ordered[e, q] > best[f]:
                best[f] = ordered[e, q]
                owner[f] = e * taps + q
    flat = owned.reshape(-1)
    for f in range(pixels):
        if owner[f] >= 0:
            flat[owner[f]] = True


def owner_slots(feet: Footprints) -> np.ndarray:
    """(P,): each masked frame pixel's owning slot, into the flattened (E, K) footprints."""
    slots = np.flatnonzero(feet.owned.ravel())
    # every masked pixel has exactly one owner, so the owned slots' pixels are a permutation of 0 … P − 1
    owner = np.empty_like(slots)
    owner[feet.pixel.ravel()[slots]] = slots
    return owner


def _ring(light: RingLight) -> tuple[float, ...]:
    """The ring light as the kernels take it: (cos e, sin e, phase φ0 in rad, ω in rad/µs, t0 in µs),
    azimuth φ(t) = φ0 + ω·(t − t0) at elevation e; then, as the closed form of ``Renderer`` needs them
    for the half vector h = l + v (whose length does not change on the ring), 1/|h|, |h|²/(|h|² + ε)
    and ε/(|h|² + ε)."""
    e = math.radians(light.elevation_deg)
    omega = light.sense * 2.0 * math.pi / light.period_us
    cos_e, sin_e = math.cos(e), math.sin(e)
    hh = cos_e * cos_e + (1.0 + sin_e) ** 2
    return (cos_e, sin_e, math.radians(light.phase_deg), omega, float(light.t0_us), 1.0 / math.sqrt(hh + HALF_EPS),
            hh / (hh + HALF_EPS), HALF_EPS / (hh + HALF_EPS))


def _shadow_table(renderer: Renderer, ta: float, tb: float) -> tuple[np.ndarray, np.ndarray, tuple[float, float]]:
    """Unclipped visibility (``pstoolkit.sim.shadow_sweep._openness`` of the shadow margins) of the frame pixels at the
    grid times around [ta, tb]: (N, H·W) float32 rows for keys first, first + 1, … (the renderer's
    sweep buffer, valid until its next sweep), which of them are column-major (N,) (see
    ``Renderer.frame_openness``), and the grid (step µs, first key): V at a time is the linear mix
    of the two rows around it, clipped to [0, 1]. Without cast shadows two rows of ones (V = 1
    everywhere)."""
    if not renderer.shadows:
        return (np.ones((2, renderer.maps.height * renderer.maps.width), dtype=np.float32), np.zeros(2, np.bool_),
                (1.0, 0.0))
    step = float(renderer.shadow_step_us)  # type: ignore[arg-type]
    first = math.floor(ta / step)
    openness, column_major = renderer.frame_openness(np.arange(first, math.floor(tb / step) + 2))
    return openness, column_major, (step, float(first))


def _block_spans(ends: list[float], block_us: float, longest_us: float) -> list[tuple[float, float]]:
    """The blocks of time (start, end) in µs, in order: ``block_us`` long, ending on each of ``ends``
    (the windows'); a window's last stretch shorter than a quarter block joins the block before when
    that stays within ``longest_us``."""
    spans = []
    ta = 0.0
    for end in ends:
        while ta < end:
            tb = min(end, ta + block_us)
            if end - tb < 0.25 * block_us and end - ta <= longest_us:
                tb = end
            spans.append((ta, tb))
            ta = tb
    return spans


def _grid_light(ring: tuple, rows: int, grid: tuple[float, float]) -> np.ndarray:
    """For ``_lit_shadow``, (3, rows): per grid time of a shadow table, the light's x and y and how far
    n·l may exceed the larger of its values at neighbouring grid times (``cos e·(ω·step)²``)."""
    cos_e, _, phase, omega, t0 = ring[:5]
    phi = phase + omega * ((grid[1] + np.arange(rows)) * grid[0] - t0)
    slack = np.full(rows, cos_e * (omega * grid[0]) ** 2)
    return np.stack([cos_e * np.cos(phi), cos_e * np.sin(phi), slack])


def simulate_ring(
    renderer: Renderer,
    *,
    event_scale: float,
    t1_us: float,
    window_ends_us: list[float],
    contrast_pos: float,
    contrast_neg: float,
    sigma: float = 0.0,
    refractory_us: float = 0.0,
    seed: int = 0,
    min_dt_us: float = 1.0,
    max_dt_us: float | None = None,
    max_dlog: float | None = None,
    eps: float = LOG_EPS,
    block_us: float | None = None,
    capacity: int | None = None,
    refractory_rule: str = REFRACTORY_RULE,
) -> Iterator[Block]:
    """Events of the event sensor at ``event_scale`` over [0, ``t1_us``] and the exposure sums of the
    windows ending at ``window_ends_us`` (increasing, inside (0, t1_us]), block by block in time
    order (see the module docstring). ``renderer`` must be ``supported``. ``max_dlog`` defaults to
    half the smaller contrast, ``max_dt_us`` (the longest step away from the shadow-grid intervals in
    which a cast shadow falls on the pixel while it is lit; around those it steps at most one) to
    ``MAX_STEP_TURNS`` of the turn, ``block_us`` to ``BLOCK_GRID_STEPS`` shadow-grid intervals (at
    most ``TABLE_ROWS`` − 3);
    ``capacity`` is the first room for events per pixel and block (grown as needed; by default
    ``FIRST_ROOM`` within ``ROOM_BYTES``); ``refractory_rule`` is one of
    ``pstoolkit.events.rule.REFRACTORY_RULES`` (with R = 0 both are ESIM's rule, run as "reset-at-end").
    Thresholds are drawn as ``pstoolkit.sim.esim`` draws them for ``seed``."""
    if not supported(renderer):
        raise UserError("simulate_ring needs a ring light, the ggx or lambertian BRDF, the CPU and a shadow grid")
    light = renderer.light
    assert isinstance(light, RingLight)
    if max_dlog is None:
        max_dlog = 0.5 * min(contrast_pos, contrast_neg)
    height, width = event_shape(renderer.maps.height, renderer.maps.width, event_scale)
    check_options(0.0, t1_us, width, height, {"contrast_pos": contrast_pos, "contrast_neg": contrast_neg}, sigma,
                  refractory_us, eps, max_dlog, 1.0, 2, min_dt_us, {}, caller="simulate_ring")
    paced = check_rule(refractory_rule, "simulate_ring") == REFRACTORY_RULES[1] and refractory_us > 0
    ends = sorted({float(t) for t in window_ends_us} | {float(t1_us)})
    if ends[0] <= 0 or ends[-1] > t1_us:
        raise UserError(f"simulate_ring: window ends must lie in (0, t1_us = {t1_us}]")
    grid_dt_us = float(renderer.shadow_step_us or light.period_us / 360.0)
    if max_dt_us is None:
        max_dt_us = light.period_us * MAX_STEP_TURNS
    longest_us = (TABLE_ROWS - 3) * grid_dt_us
    block_us = min(BLOCK_GRID_STEPS * grid_dt_us if block_us is None else float(block_us), longest_us)
    constants = frame_constants(renderer)
    feet = footprints(renderer, event_scale)
    owner = owner_slots(feet)
    n_events = height * width
    c_pos, c_neg = draw_thresholds(event_rngs(seed)[0], contrast_pos, contrast_neg, sigma, n_events)
    ring = _ring(light)
    index_t = renderer.column_major_index
    spans = _block_spans(ends, block_us, longest_us)
    # the first block's table serves the start too
    openness, column_major, grid = _shadow_table(renderer, *spans[0])
    # without cast shadows the table of ones stays, and no pixel is shadowed while lit
    reach = np.zeros(openness.shape[1], np.uint64)
    state = PixelState(
        level=np.empty(n_events), hi=np.empty(n_events), lo=np.empty(n_events),
        blind_until_us=np.full(n_events, -np.inf if paced else np.inf), step_us=np.full(n_events, max_dt_us / 4.0),
        slope=np.full(n_events, np.nan), shade=np.zeros((*feet.pixel.shape, 2)), sums=np.zeros((*feet.pixel.shape, 2)),
    )
    _start(0.0, constants.values, feet.weight, feet.pixel, renderer.index, index_t, constants.specular, ring, openness,
           column_major, grid, renderer.shadows, eps, state.level, state.shade)
    state.hi[:] = state.level + c_pos
    state.lo[:] = state.level - c_neg
    if capacity is None:
        capacity = min(FIRST_ROOM, ROOM_BYTES // (9 * n_events))
    capacity = max(1, int(capacity))
    out_t = np.empty((n_events, capacity), dtype=np.int64)
    out_p = np.empty((n_events, capacity), dtype=np.int8)
    count = np.zeros(n_events, dtype=np.int64)
    everyone = np.arange(n_events)
    for block, (ta, tb) in enumerate(spans):
        if renderer.shadows:
            if block:
                openness, column_major, grid = _shadow_table(renderer, ta, tb)
            reach = _lit_shadow(constants.values, renderer.index, index_t, ring[1], openness, column_major,
                                _grid_light(ring, openness.shape[0], grid))
        order = everyone
        while True:
            _advance(order, ta, tb, constants.values, feet.weight, feet.pixel, renderer.index, index_t,
                     constants.specular, ring, openness, column_major, grid, reach, c_pos, c_neg,
                     float(refractory_us), paced, float(eps), float(max_dlog), float(min_dt_us), float(max_dt_us),
                     grid_dt_us, state.level, state.hi, state.lo, state.blind_until_us, state.step_us,
                     state.slope, state.shade, state.sums, out_t, out_p, count, numba.get_num_threads())
            order = np.flatnonzero(count > capacity)
            if order.size == 0:
                break
            # pixels fired more than there was room for: widen the room and run them again
            most = int(count.max())
            capacity = most + most // 2
            out_t = np.concatenate([out_t, np.empty((n_events, capacity - out_t.shape[1]), np.int64)], axis=1)
            out_p = np.concatenate([out_p, np.empty((n_events, capacity - out_p.shape[1]), np.int8)], axis=1)
        x, y, t, p = _gather(out_t, out_p, count, width, math.floor(ta + 0.5), math.floor(tb + 0.5))
        sums = None
        if tb in window_ends_us:
            sums = np.take(state.sums.reshape(-1, 2), owner, axis=0)
            state.sums[:] = 0.0
        yield Block(EventArray(x=x, y=y, t=t, p=p), tb, sums)
