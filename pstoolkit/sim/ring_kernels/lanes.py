"""A thread's ``LANES`` event pixels stepped at once: each lane's state sits at its index of arrays
across the lanes, so shading, log and the light's turn run as SIMD loops. A lane holds its pixel's
frame-pixel constants per slot of the footprint (``LaneSlots``, loaded by ``load_lane``)."""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np

from pstoolkit.sim.ring_kernels.inputs import (
    ALPHA2_1,
    GREY_DIFFUSE,
    GREY_SPECULAR,
    NORM2,
    NX,
    NY,
    NZ,
    ONE_K,
    VIEW,
    FrameInputs,
    RingParams,
    ShadowTable,
)
from pstoolkit.sim.ring_kernels.inputs import K as K_COLUMN
from pstoolkit.sim.ring_kernels.tuning import LANES


class LaneSlots(NamedTuple):
    """The lanes' slots: per slot q and lane k the frame pixel's ``FrameConstants`` columns ``values``
    (10, K, W), with the greys times the slot's area weight, and its flat frame position row- and
    column-major, ``position`` and ``position_t`` (K, W)."""

    values: np.ndarray
    position: np.ndarray
    position_t: np.ndarray


# Direction of the ring light: a lane turns it from the azimuth at its last sample by the step's angle
# (at most ``MAX_STEP_TURNS`` of the turn, 0.14 rad) with the series of cos and sin, whose first
# omitted terms are below 1e-18: cheaper than the library's cos and sin, and SIMD.
@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def turn(d: float) -> tuple[float, float]:  # pragma: no cover - compiled
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
def log_lanes(
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
def shade_lanes(
    t1: np.ndarray, cos_az: np.ndarray, sin_az: np.ndarray, slots: LaneSlots, shadows: np.ndarray, specular: bool,
    ring: RingParams, table: ShadowTable, eps: float, now: np.ndarray, grey: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """Grey irradiance + ``eps`` of each lane's event pixel at its time ``t1`` into ``grey`` (W,),
    the light at azimuth (``cos_az``, ``sin_az``); ``now`` (2, K, W) gets each slot's V·[n·l]₊ and
    V·[n·l]₊·ratio. V is read from ``table`` only where a lane's ``shadows`` (W,) has the bit of the
    table interval of its time (``lit_shadow``'s bits of its frame pixels): elsewhere V ≥ 1 at both
    ends of the interval, or the pixels face away from the light through it, and V changes nothing.
    The loops run across the lanes, so they compile to SIMD."""
    consts, frame, frame_t = slots.values, slots.position, slots.position_t
    openness, column_major = table.openness, table.column_major
    cos_e, sin_e, inv_h, hh, lift = ring.cos_e, ring.sin_e, ring.inv_half, ring.half_share, ring.eps_share
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
            ratio = consts[VIEW, q, k] / (d * d * (consts[K_COLUMN, q, k] + nl * consts[ONE_K, q, k]))
            lit = nl > 0.0
            now[0, q, k] = nl if lit else 0.0
            now[1, q, k] = ratio if lit and specular else 0.0
    rows = openness.shape[0]
    for k in range(lanes):
        if shadows[k] == 0:
            continue
        x = t1[k] / table.grid_step_us - table.grid_first
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
    consts: np.ndarray, position: np.ndarray, position_t: np.ndarray, q: int, k: int,
) -> None:  # pragma: no cover - compiled
    """Slot ``q`` of lane ``k`` without a frame pixel (``LaneSlots``' arrays): constants of zero (no
    light), but |n|² and k of one, which keep its shading finite, at frame position 0."""
    for col in range(consts.shape[0]):
        consts[col, q, k] = 0.0
    consts[NORM2, q, k] = 1.0
    consts[K_COLUMN, q, k] = 1.0
    position[q, k] = 0
    position_t[q, k] = 0


@numba.njit(cache=True, nogil=True, error_model="numpy")
def idle_lanes(columns: int, taps: int) -> LaneSlots:  # pragma: no cover - compiled
    """The slots of ``LANES`` lanes without a pixel (``_idle_slot``): ``columns`` constants and ``taps``
    slots each."""
    slots = LaneSlots(np.empty((columns, taps, LANES)), np.empty((taps, LANES), np.int64), np.empty((taps, LANES), np.int64))
    for q in range(taps):
        for k in range(LANES):
            _idle_slot(slots.values, slots.position, slots.position_t, q, k)
    return slots


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def load_lane(slots: LaneSlots, k: int, p: int, frame: FrameInputs) -> None:  # pragma: no cover - compiled
    """Lane ``k`` takes event pixel ``p``: per slot of its footprint (``Footprints``), the frame
    pixel's ``FrameConstants.values`` with the greys times the slot's area weight, and its flat
    positions row- and column-major; an unused slot is idle (``_idle_slot``: adds nothing).

    Every array is taken out of its record once, before the loop: each read of a record's array
    field is a reference count taken and dropped (atomic), too slow for the loop."""
    consts, position, position_t = slots.values, slots.position, slots.position_t
    values, weight, pixel, index, index_t = frame.values, frame.weight, frame.pixel, frame.index, frame.index_t
    for q in range(pixel.shape[1]):
        f = pixel[p, q]
        if f < 0:
            _idle_slot(consts, position, position_t, q, k)
            continue
        for col in range(values.shape[1]):
            consts[col, q, k] = values[f, col]
        consts[GREY_DIFFUSE, q, k] *= weight[p, q]
        consts[GREY_SPECULAR, q, k] *= weight[p, q]
        position[q, k] = index[f]
        position_t[q, k] = index_t[f]
