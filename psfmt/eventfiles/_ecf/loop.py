"""The ECF decoder as one loop per chunk (the reference; numba compiles it where installed).

``decode_loop`` decodes chunks ``k`` of ``buf[starts[k]:ends[k]]`` holding ``counts[k]`` events into
the output columns from ``at[k]`` on, and sets ``status[k]`` to a code of ``psfmt.eventfiles._ecf.chunk``
(``OK`` or the first fault met). Chunks are independent, so callers split them across threads.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import numpy as np

from psfmt.eventfiles._ecf.chunk import LONG_DELTA, MAX_DIGITS, MODE_PACKED, MODE_PACKED_XP, OK, OUTSIDE, OVERRUN, SHORT, TIME_BACK


def _u16(buf, pos):  # type: ignore[no-untyped-def]
    return np.int64(buf[pos]) | (np.int64(buf[pos + 1]) << 8)


def _u32(buf, pos):  # type: ignore[no-untyped-def]
    return _u16(buf, pos) | (_u16(buf, pos + 2) << 16)


def _put(v, k, width, height, x, y, p):  # type: ignore[no-untyped-def]
    """Store the packed value ``y << 12 | x << 1 | p`` as event ``k``; False if outside the sensor."""
    ex, ey = (v >> 1) & 0x7FF, (v >> 12) & 0x7FF
    if ex >= width or ey >= height:
        return False
    x[k], y[k], p[k] = ex, ey, 2 * (v & 1) - 1
    return True


def _times(buf, pos, end, n, o, t):  # type: ignore[no-untyped-def]
    """Fill ``t[o:o + n]``; (position after the times, status). Times add up in int64 with
    wrap-around, as unsigned 64-bit sums: a sum below its predecessor went past 2⁶³ - 1."""
    if pos + 8 > end:
        return pos, SHORT
    now = _u32(buf, pos) | (_u32(buf, pos + 4) << 32)
    pos += 8
    i = 0
    while i < n:
        if pos >= end:
            return pos, SHORT
        c = np.int64(buf[pos])
        pos += 1
        delta = c >> 4
        if delta == 15:
            delta = 0
            shift = 0
            while (c >> 4) == 15:
                if shift >= 4 * MAX_DIGITS:
                    return pos, LONG_DELTA
                delta |= (c & 15) << shift
                shift += 4
                if pos >= end:
                    return pos, SHORT
                c = np.int64(buf[pos])
                pos += 1
            if (c >> 4) != 0:
                if shift >= 4 * MAX_DIGITS:
                    return pos, LONG_DELTA
                delta |= (c >> 4) << shift
        after = now + delta
        if after < now:
            return pos, TIME_BACK
        now = after
        count = c & 15
        if count == 15:
            if pos + 2 > end:
                return pos, SHORT
            count = _u16(buf, pos)
            pos += 2
        if count > n - i:
            return pos, OVERRUN
        for k in range(o + i, o + i + count):
            t[k] = now
        i += count
    return pos, OK


def _rows(buf, pos, end, n, o, height, y):  # type: ignore[no-untyped-def]
    i = 0
    while i < n:
        if pos + 2 > end:
            return pos, SHORT
        w = _u16(buf, pos)
        pos += 2
        row, count = w >> 5, w & 31
        if count == 31:
            if pos + 2 > end:
                return pos, SHORT
            count = _u16(buf, pos)
            pos += 2
        if count > n - i:
            return pos, OVERRUN
        if row >= height:
            return pos, OUTSIDE
        for k in range(o + i, o + i + count):
            y[k] = row
        i += count
    return pos, OK


def _packed(buf, pos, end, n, o, width, height, x, y, p):  # type: ignore[no-untyped-def]
    if pos + 12 * ((n + 3) // 4) > end:
        return SHORT
    for g in range(0, n, 4):
        w0, w1, w2 = _u32(buf, pos), _u32(buf, pos + 4), _u32(buf, pos + 8)
        pos += 12
        left = n - g
        if not _put(w0 >> 8, o + g, width, height, x, y, p):
            return OUTSIDE
        if left > 1 and not _put((w0 & 0xFF) | ((w1 >> 16) << 8), o + g + 1, width, height, x, y, p):
            return OUTSIDE
        if left > 2 and not _put((w1 & 0xFFFF) | ((w2 >> 24) << 16), o + g + 2, width, height, x, y, p):
            return OUTSIDE
        if left > 3 and not _put(w2 & 0xFFFFFF, o + g + 3, width, height, x, y, p):
            return OUTSIDE
    return OK


def _packed_xp(buf, pos, end, n, o, width, x, p):  # type: ignore[no-untyped-def]
    if pos + 6 * ((n + 3) // 4) > end:
        return SHORT
    for g in range(0, n, 4):
        w0, w1, w2 = _u16(buf, pos), _u16(buf, pos + 2), _u16(buf, pos + 4)
        pos += 6
        for j in range(min(4, n - g)):
            if j == 0:
                v = w0 >> 4
            elif j == 1:
                v = (w0 & 0xF) | ((w1 >> 8) << 4)
            elif j == 2:
                v = (w1 & 0xFF) | ((w2 >> 12) << 8)
            else:
                v = w2 & 0xFFF
            if (v >> 1) >= width:
                return OUTSIDE
            x[o + g + j] = v >> 1
            p[o + g + j] = 2 * (v & 1) - 1
    return OK


def _masked_x(buf, pos, end, n, o, width, x):  # type: ignore[no-untyped-def]
    i = 0
    while i < n:
        if pos + 2 > end:
            return pos, SHORT
        w = _u16(buf, pos)
        pos += 2
        base = w >> 5
        if base + 5 >= width:
            # near the sensor's edge: every event checked one by one
            if base >= width:
                return pos, OUTSIDE
            x[o + i] = base
            i += 1
            for k in range(5):
                if i < n and (w >> (4 - k)) & 1:
                    if base + 1 + k >= width:
                        return pos, OUTSIDE
                    x[o + i] = base + 1 + k
                    i += 1
        elif i + 6 <= n:
            # without branches: each slot is written, and kept when its mask bit is set
            j = o + i
            x[j] = base
            j += 1
            x[j] = base + 1
            j += (w >> 4) & 1
            x[j] = base + 2
            j += (w >> 3) & 1
            x[j] = base + 3
            j += (w >> 2) & 1
            x[j] = base + 4
            j += (w >> 1) & 1
            x[j] = base + 5
            j += w & 1
            i = j - o
        else:
            x[o + i] = base
            i += 1
            for k in range(5):
                if i < n and (w >> (4 - k)) & 1:
                    x[o + i] = base + 1 + k
                    i += 1
    return pos, OK


def _polarity_runs(buf, pos, end, n, o, p):  # type: ignore[no-untyped-def]
    i = 0
    while i < n:
        if pos >= end:
            return SHORT
        c = np.int64(buf[pos])
        pos += 1
        count = c & 127
        if count == 127:
            if pos + 2 > end:
                return SHORT
            count = _u16(buf, pos)
            pos += 2
        if count > n - i:
            return OVERRUN
        pol = 2 * (c >> 7) - 1
        for k in range(o + i, o + i + count):
            p[k] = pol
        i += count
    return OK


def _chunk(buf, start, end, n, o, width, height, x, y, t, p):  # type: ignore[no-untyped-def]
    mode = buf[start] & 3
    pos, status = _times(buf, start + 4, end, n, o, t)
    if status != OK:
        return status
    if mode & MODE_PACKED:
        return _packed(buf, pos, end, n, o, width, height, x, y, p)
    pos, status = _rows(buf, pos, end, n, o, height, y)
    if status != OK:
        return status
    if mode & MODE_PACKED_XP:
        return _packed_xp(buf, pos, end, n, o, width, x, p)
    pos, status = _masked_x(buf, pos, end, n, o, width, x)
    if status != OK:
        return status
    return _polarity_runs(buf, pos, end, n, o, p)


def decode_loop(buf, starts, ends, counts, at, width, height, x, y, t, p, status):  # type: ignore[no-untyped-def]
    """Decode every chunk listed into the columns (x, y uint16; t int64 µs; p int8 ±1); ``status``
    gets each chunk's code."""
    for k in range(starts.shape[0]):
        status[k] = _chunk(buf, starts[k], ends[k], counts[k], at[k], width, height, x, y, t, p)


_HELPERS = ("_u16", "_u32", "_put", "_times", "_rows", "_packed", "_packed_xp", "_masked_x", "_polarity_runs", "_chunk")


@functools.cache
def compiled() -> Callable[..., Any]:
    """``decode_loop`` compiled by numba (cached on disk, releasing the GIL so that threads decode
    chunks side by side); numba is imported on the first call only."""
    import numba

    njit = numba.njit(cache=True, nogil=True)
    names = globals()
    for name in _HELPERS:  # the kernel calls its helpers through the module's globals
        names[name] = njit(names[name])
    return njit(decode_loop)
