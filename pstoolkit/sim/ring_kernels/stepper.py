"""The ring-light engine's time stepping: each event pixel advances through a block of time in its
own adaptive steps (``advance_pixels``, ``LANES`` pixels at once), in parallel over event pixels
(``advance``); ``start`` gives every pixel its level and shading at the start of the simulation."""

from __future__ import annotations

import math

import numba
import numpy as np

from pstoolkit._shared.worksharing import take_task
from pstoolkit.sim.ring_kernels.firing import (
    FIRE_COUNT,
    PACED_COUNT,
    PACED_ROWS,
    emit,
    emit_paced,
    fire_lanes,
    fire_lanes_paced,
)
from pstoolkit.sim.ring_kernels.inputs import EventRoom, EventRule, FrameInputs, PixelState, RingParams, ShadowTable, StepLimits
from pstoolkit.sim.ring_kernels.lanes import idle_lanes, load_lane, log_lanes, shade_lanes, turn
from pstoolkit.sim.ring_kernels.shadow_table import shadow_room
from pstoolkit.sim.ring_kernels.tuning import LANES, MAX_BEND, PIXELS_PER_TASK


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def next_try(h: float, left: float, min_dt: float) -> float:  # pragma: no cover - compiled
    """The step to try next: ``h``, or all that is ``left`` of the block when ``h`` reaches it or
    would leave less than ``min_dt`` of it."""
    return left if (h >= left or left - h < min_dt) else h


@numba.njit(cache=True, nogil=True, error_model="numpy")
def advance_pixels(
    order: np.ndarray, first: int, last: int, ta: float, tb: float, frame: FrameInputs, ring: RingParams,
    table: ShadowTable, rule: EventRule, limits: StepLimits, state: PixelState, room: EventRoom,
) -> None:  # pragma: no cover - compiled
    """Event pixels ``order[first:last]`` from ``ta`` to ``tb``, ``LANES`` at a time: each lane
    steps its own pixel, and a lane's state sits at its index of arrays across the lanes, so the
    shading, the log, the step control and the firing rule of all lanes run as SIMD loops; only the
    lanes that store events, finish or have cast shadows near take scalar turns. The firing rule
    is "rate-limited" when ``rule.paced`` (``fire_lanes_paced``), else "reset-at-end" (``fire_lanes``)."""
    pixel, specular, reach = frame.pixel, frame.specular, table.reach
    c_pos, c_neg, refractory_us, paced, eps = rule.c_pos, rule.c_neg, rule.refractory_us, rule.paced, rule.eps
    leak_per_us, leaky = rule.leak_per_us, rule.leaky
    max_dlog, min_dt, max_dt, grid_dt = limits.max_dlog, limits.min_dt_us, limits.max_dt_us, limits.grid_dt_us
    level, hi, lo, blind_until, step, slope = state.level, state.hi, state.lo, state.blind_until_us, state.step_us, state.slope
    shade, sums, out_t, out_p, count = state.shade, state.sums, room.t_us, room.polarity, room.count
    taps = pixel.shape[1]
    w = LANES
    omega, t0, phase = ring.omega_rad_per_us, ring.t0_us, ring.phase_rad
    cos_a, sin_a = math.cos(phase + omega * (ta - t0)), math.sin(phase + omega * (ta - t0))
    lane = np.zeros(w, np.int64)
    active = np.zeros(w, np.bool_)
    # a lane's pixel state (as ``PixelState``) and the azimuth at its last sample
    t, l0, s0, h, h_try = np.full(w, tb), np.zeros(w), np.zeros(w), np.zeros(w), np.ones(w)
    l_hi, l_lo, l_blind, l_pos, l_neg = np.zeros(w), np.zeros(w), np.zeros(w), np.zeros(w), np.zeros(w)
    l_leak = np.zeros(w)
    n = np.zeros(w, np.int64)
    shadows = np.zeros(w, np.uint64)
    cos_az, sin_az = np.ones(w), np.zeros(w)
    slots = idle_lanes(frame.values.shape[1], taps)
    position = slots.position
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
            load_lane(slots, k, p, frame)
            # a pixel on which no cast shadow falls while lit during the block skips the table, and
            # one whose shadows come and go steps short only around them
            shadows[k] = 0
            for q in range(taps):
                if pixel[p, q] >= 0:
                    shadows[k] |= reach[position[q, k]]
                for j in range(2):
                    last_shade[j, q, k] = shade[p, q, j]
                    l_sums[j, q, k] = sums[p, q, j]
            t[k], l0[k], s0[k], n[k] = ta, level[p], slope[p], 0
            l_hi[k], l_lo[k], l_blind[k], l_pos[k], l_neg[k] = hi[p], lo[p], blind_until[p], c_pos[p], c_neg[p]
            l_leak[k] = leak_per_us[p]
            cos_az[k], sin_az[k] = cos_a, sin_a
            h[k] = min(step[p], shadow_room(ta, shadows[k], table, grid_dt, max_dt))
            h_try[k] = next_try(h[k], tb - ta, min_dt)
        if not active.any():
            break
        # the trial samples: time, azimuth turned on from the last sample, shading, log
        for k in range(w):
            t1[k] = tb if h_try[k] >= tb - t[k] else t[k] + h_try[k]
            cos_d, sin_d = turn(omega * (t1[k] - t[k]))
            cos1[k] = cos_az[k] * cos_d - sin_az[k] * sin_d
            sin1[k] = sin_az[k] * cos_d + cos_az[k] * sin_d
        shade_lanes(t1, cos1, sin1, slots, shadows, specular, ring, table, eps, now, grey)
        log_lanes(grey, l1, exponent, mantissa)
        if leaky:
            # the leak: L drifts up against the reference (v2e's leak, as a drift of the signal)
            for k in range(w):
                l1[k] += l_leak[k] * t1[k]
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
            fire_lanes_paced(accepted, t, l0, t1, l1, l_pos, l_neg, refractory_us, l_hi, l_lo, l_blind, fire)
            for k in range(w):
                if fire[PACED_COUNT, k] > 0 or fire[PACED_ROWS + PACED_COUNT, k] > 0:
                    p = lane[k]
                    n[k] = emit_paced(fire, k, refractory_us, out_t[p], out_p[p], n[k])
        else:
            fire_lanes(accepted, t, l0, t1, l1, l_pos, l_neg, refractory_us, l_hi, l_lo, l_blind, fire)
            for k in range(w):
                if fire[FIRE_COUNT, k] > 0:
                    p = lane[k]
                    n[k] = emit(fire, k, t[k], t1[k], out_t[p], out_p[p], n[k])
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
            h_try[k] = next_try(h[k], tb - t[k], min_dt) if a else h_try[k]
        for k in range(w):
            if not accepted[k]:
                continue
            if shadows[k]:
                h[k] = min(shadow_room(t[k], shadows[k], table, grid_dt, max_dt), grown[k])
                h_try[k] = next_try(h[k], tb - t[k], min_dt)
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
def advance(
    order: np.ndarray, ta: float, tb: float, frame: FrameInputs, ring: RingParams, table: ShadowTable, rule: EventRule,
    limits: StepLimits, state: PixelState, room: EventRoom, threads: int,
) -> None:  # pragma: no cover - compiled
    """The event pixels ``order`` from ``ta`` to ``tb`` (``advance_pixels``), ``PIXELS_PER_TASK`` to a
    task, each of the ``threads`` (numba's) taking the next task as it comes free
    (``pstoolkit._shared.worksharing``); ``state`` is updated in place, events and their numbers go to
    ``room``."""
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
            advance_pixels(order, first, min(first + PIXELS_PER_TASK, order.shape[0]), ta, tb, frame, ring, table, rule,
                           limits, state, room)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def start(
    t_us: float, frame: FrameInputs, ring: RingParams, table: ShadowTable, shadows: bool, eps: float, state: PixelState,
) -> None:  # pragma: no cover - compiled
    """Levels and slot shading at ``t_us`` (the start of the simulation), ``LANES`` pixels at a time
    as ``advance_pixels`` shades them."""
    pixel, level, shade = frame.pixel, state.level, state.shade
    taps = pixel.shape[1]
    slots = idle_lanes(frame.values.shape[1], taps)
    azimuth = ring.phase_rad + ring.omega_rad_per_us * (t_us - ring.t0_us)
    t1, cos_az, sin_az = np.full(LANES, t_us), np.full(LANES, math.cos(azimuth)), np.full(LANES, math.sin(azimuth))
    # every interval, or none without cast shadows
    every = np.full(LANES, np.uint64(0xFFFFFFFFFFFFFFFF) if shadows else np.uint64(0))
    now, grey, l1 = np.zeros((2, taps, LANES)), np.empty(LANES), np.empty(LANES)
    exponent, mantissa = np.empty(LANES, np.int64), np.empty(LANES, np.int64)
    for first in range(0, pixel.shape[0], LANES):
        used = min(LANES, pixel.shape[0] - first)
        for k in range(used):
            load_lane(slots, k, first + k, frame)
        shade_lanes(t1, cos_az, sin_az, slots, every, frame.specular, ring, table, eps, now, grey)
        log_lanes(grey, l1, exponent, mantissa)
        for k in range(used):
            level[first + k] = l1[k]
            for q in range(taps):
                for j in range(2):
                    shade[first + k, q, j] = now[j, q, k]
