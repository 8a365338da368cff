"""The EVT 3.0 decoder's kernel: words and a carried state in, events, triggers and counters out.

The state is an int64 array laid out as ``DECODER_STATE``; the counters an int64 array of six, in
the order ``DecodeStats.add_counters`` takes them: words of the skipped types, words of unknown type,
event and trigger words before the first TIME_HIGH, event words before the first ADDR_Y, vector words
before the first VECT_BASE_X, and events outside the sensor. ``decode_loop`` is the reference (numba
compiles it for ``decode_numba``); ``decode_numpy`` gives the same results with whole-array
operations.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np

from psfmt.eventfiles._evt3.engine import jit
from psfmt.eventfiles._evt3.words import ADDR_X, ADDR_Y, EXT_TRIGGER, SKIPPED_TYPES, TIME_HIGH, TIME_LOW, VECT_8, VECT_12, VECT_BASE_X, WRAP_DROP
from psfmt.events import EventArray, Triggers

DECODER_STATE = (0, 0, 0, 0, -1, -1, 0)
"""The state before the first word: have_high, high, wraps, low, y (-1: none yet), base_x (-1: none yet), base_p."""


def decode_loop(words, state, counters, width, height, ox, oy, ot, op, tt, tc, tv):  # type: ignore[no-untyped-def]
    """Decode ``words`` from ``state`` into the output arrays until the words or the room run out;
    returns (events written, triggers written, words consumed) and updates ``state`` and ``counters``
    (others, unknown, no_time, no_y, no_base, outside)."""
    have_high, high, wraps, low, y, bx, bp = state[0], state[1], state[2], state[3], state[4], state[5], state[6]
    others, unknown, no_time, no_y, no_base, outside = counters[0], counters[1], counters[2], counters[3], counters[4], counters[5]
    cap, tcap = ox.shape[0], tt.shape[0]
    now = (wraps << 24) | (high << 12) | low  # the time of the next event, kept up to date
    n = 0
    m = 0
    i = 0
    while i < words.shape[0]:
        if n + 12 > cap or m >= tcap:
            break
        w = np.int64(words[i])
        typ = w >> 12
        if typ == ADDR_X:
            x = w & 0x7FF
            if have_high != 0 and y >= 0 and x < width and y < height:
                ox[n] = x
                oy[n] = y
                ot[n] = now
                op[n] = ((w >> 10) & 2) - 1
                n += 1
            elif have_high == 0:
                no_time += 1
            elif y < 0:
                no_y += 1
            else:
                outside += 1
        elif typ == ADDR_Y:
            y = w & 0x7FF
        elif typ == TIME_LOW:
            low = w & 0xFFF
            now = (wraps << 24) | (high << 12) | low
        elif typ == VECT_12 or typ == VECT_8:
            nbits = 12 if typ == VECT_12 else 8
            if bx < 0:
                no_base += 1
            else:
                if have_high == 0:
                    no_time += 1
                elif y < 0:
                    no_y += 1
                else:
                    bits = w & ((1 << nbits) - 1)
                    pol = 1 if bp else -1
                    if bx + nbits <= width and y < height:
                        # every slot written, the count moved on by its bit: no branch per bit
                        for k in range(nbits):
                            ox[n] = bx + k
                            oy[n] = y
                            ot[n] = now
                            op[n] = pol
                            n += (bits >> k) & 1
                    else:
                        for k in range(nbits):
                            if (bits >> k) & 1:
                                x = bx + k
                                if x >= width or y >= height:
                                    outside += 1
                                else:
                                    ox[n] = x
                                    oy[n] = y
                                    ot[n] = now
                                    op[n] = pol
                                    n += 1
                bx += nbits
        elif typ == VECT_BASE_X:
            bx = w & 0x7FF
            bp = (w >> 11) & 1
        elif typ == TIME_HIGH:
            h = w & 0xFFF
            if have_high == 0:
                have_high = 1
                low = 0
            elif h != high:
                if high - h >= WRAP_DROP:
                    wraps += 1
                low = 0
            high = h
            now = (wraps << 24) | (high << 12) | low
        elif typ == EXT_TRIGGER:
            if have_high == 0:
                no_time += 1
            else:
                tt[m] = now
                tc[m] = (w >> 8) & 0xF
                tv[m] = w & 1
                m += 1
        elif typ == 0x7 or typ == 0xE or typ == 0xF:
            others += 1
        else:
            unknown += 1
        i += 1
    state[0], state[1], state[2], state[3], state[4], state[5], state[6] = have_high, high, wraps, low, y, bx, bp
    counters[0], counters[1], counters[2], counters[3], counters[4], counters[5] = others, unknown, no_time, no_y, no_base, outside
    return n, m, i


_decode_loop_compiled = jit(decode_loop)


def advance_loop(words, state):  # type: ignore[no-untyped-def]
    """Move ``state`` over ``words`` exactly as ``decode_loop`` would, writing nothing: what a thread
    decoding the words after them starts from."""
    have_high, high, wraps, low, y, bx, bp = state[0], state[1], state[2], state[3], state[4], state[5], state[6]
    for i in range(words.shape[0]):
        w = np.int64(words[i])
        typ = w >> 12
        if typ == ADDR_Y:
            y = w & 0x7FF
        elif typ == TIME_LOW:
            low = w & 0xFFF
        elif typ == VECT_12 or typ == VECT_8:
            if bx >= 0:
                bx += 12 if typ == VECT_12 else 8
        elif typ == VECT_BASE_X:
            bx = w & 0x7FF
            bp = (w >> 11) & 1
        elif typ == TIME_HIGH:
            h = w & 0xFFF
            if have_high == 0:
                have_high = 1
                low = 0
            elif h != high:
                if high - h >= WRAP_DROP:
                    wraps += 1
                low = 0
            high = h
    state[0], state[1], state[2], state[3], state[4], state[5], state[6] = have_high, high, wraps, low, y, bx, bp


_advance_loop_compiled = jit(advance_loop)


class Output:
    """Event and trigger columns that the compiled loop fills, grown as it needs: decoding a whole
    file into one such output spares a concatenation of per-block parts (a copy of every event)."""

    def __init__(self, events: int, triggers: int = 1 << 10) -> None:
        self.x, self.y = np.empty(max(12, events), np.uint16), np.empty(max(12, events), np.uint16)
        self.t, self.p = np.empty(max(12, events), np.int64), np.empty(max(12, events), np.int8)
        self.tt, self.tc, self.tv = np.empty(triggers, np.int64), np.empty(triggers, np.uint8), np.empty(triggers, np.int8)
        self.n = self.m = 0

    def _resize(self, events: int, triggers: int) -> None:
        # in place where the allocator can (always when shrinking): no copy of what is written
        for name in ("x", "y", "t", "p"):
            getattr(self, name).resize(events, refcheck=False)
        for name in ("tt", "tc", "tv"):
            getattr(self, name).resize(triggers, refcheck=False)

    def grow(self, events: int = 0, triggers: int = 0) -> None:
        """Room for at least ``events`` and ``triggers`` more (at least half as much again)."""
        self._resize(
            max(len(self.x) + max(len(self.x) // 2, 12), self.n + events), max(2 * len(self.tt), self.m + triggers)
        )  # fmt: skip

    def append(self, other: Output) -> None:
        """Add what ``other`` holds after what this output holds."""
        if self.n + other.n > len(self.x) or self.m + other.m > len(self.tt):
            self.grow(other.n, other.m)
        for name in ("x", "y", "t", "p"):
            getattr(self, name)[self.n : self.n + other.n] = getattr(other, name)[: other.n]
        for name in ("tt", "tc", "tv"):
            getattr(self, name)[self.m : self.m + other.m] = getattr(other, name)[: other.m]
        self.n += other.n
        self.m += other.m

    def take(self) -> tuple[EventArray, Triggers]:
        """The events and triggers written, as arrays of their exact size; the output is spent."""
        self._resize(self.n, self.m)
        return EventArray(self.x, self.y, self.t, self.p), Triggers(self.tt, self.tc, self.tv)


def decode_into(words: np.ndarray, state: np.ndarray, counters: np.ndarray, width: int, height: int, out: Output) -> None:
    """Decode the uint16 ``words`` by the compiled loop into ``out`` (grown until every word is used);
    updates ``state`` and adds to ``counters``."""
    start = 0
    while start < len(words):
        n, m, used = _decode_loop_compiled(
            words[start:], state, counters, width, height, out.x[out.n :], out.y[out.n :], out.t[out.n :], out.p[out.n :],
            out.tt[out.m :], out.tc[out.m :], out.tv[out.m :],
        )  # fmt: skip
        out.n += n
        out.m += m
        start += used
        if start < len(words):
            out.grow()


def decode_parallel(words: np.ndarray, state: np.ndarray, counters: np.ndarray, width: int, height: int, out: Output) -> None:
    """``decode_into`` on two threads: the first decodes the first ~60 % of the words while the
    second moves a copy of the state over them (``advance_loop``, cheaper than decoding) and decodes
    the rest into an output of its own, appended at the end. Same events, state and counters."""
    split = (len(words) * 5) // 8
    head, tail = words[:split], words[split:]
    tail_state, tail_counters = state.copy(), np.zeros_like(counters)
    tail_out = Output(len(tail) + 12)

    def second() -> None:
        _advance_loop_compiled(head, tail_state)
        decode_into(tail, tail_state, tail_counters, width, height, tail_out)

    with ThreadPoolExecutor(1) as pool:
        job = pool.submit(second)
        decode_into(head, state, counters, width, height, out)
        job.result()
    out.append(tail_out)
    state[:] = tail_state
    counters += tail_counters


def decode_numba(words: np.ndarray, state: np.ndarray, counters: np.ndarray, width: int, height: int) -> tuple[EventArray, Triggers]:
    """The events and triggers of the uint16 ``words`` (coordinates below ``width`` × ``height``) by the
    compiled loop; updates ``state`` and adds to ``counters``."""
    out = Output(len(words) + 12)  # sensors give fewer events than words; more only grows the output
    decode_into(words, state, counters, width, height, out)
    return out.take()


def _ffill(mask: np.ndarray) -> np.ndarray:
    """For every position, the index of the last True at or before it (-1 where none)."""
    return np.maximum.accumulate(np.where(mask, np.arange(len(mask)), -1))


def _time_words(words: np.ndarray, typ: np.ndarray, state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per word: whether a TIME_HIGH has been seen and the time in µs; updates the time part of ``state``."""
    th = np.flatnonzero(typ == TIME_HIGH)
    h = (words[th] & 0xFFF).astype(np.int64)
    prev = np.concatenate([[state[1]], h[:-1]])
    had = np.ones(len(h), bool)
    if len(h):
        had[0] = bool(state[0])
    changed = ~had | (h != prev)
    wraps = state[2] + np.cumsum(had & (prev - h >= WRAP_DROP))
    base = (wraps << 24) | (h << 12)
    # the low bits come from the last TIME_LOW, or 0 from the last TIME_HIGH that changed the high
    is_tl = typ == TIME_LOW
    sets_low = is_tl.copy()
    sets_low[th[changed]] = True
    low_values = np.where(is_tl, words & 0xFFF, 0).astype(np.int64)
    last_low = _ffill(sets_low)
    low = np.where(last_low >= 0, low_values[np.maximum(last_low, 0)], state[3])
    th_rank = np.cumsum(typ == TIME_HIGH) - 1
    have = (th_rank >= 0) | bool(state[0])
    old_base = (state[2] << 24) | (state[1] << 12)
    t = np.where(th_rank >= 0, base[np.maximum(th_rank, 0)] if len(h) else 0, old_base) | low
    if len(h):
        state[0], state[1], state[2] = 1, h[-1], wraps[-1]
    if len(low):
        state[3] = low[-1]
    return have, t


def _ffill_values(mask: np.ndarray, values: np.ndarray, initial: int) -> np.ndarray:
    last = _ffill(mask)
    return np.where(last >= 0, values[np.maximum(last, 0)], initial)


def _advance_space(w: np.ndarray, typ: np.ndarray, state: np.ndarray) -> None:
    """Move the row and vector-base part of ``state`` over the words ``w``."""
    ys = np.flatnonzero(typ == ADDR_Y)
    if len(ys):
        state[4] = w[ys[-1]] & 0x7FF
    bases = np.flatnonzero(typ == VECT_BASE_X)
    tail = typ[bases[-1] + 1 :] if len(bases) else typ
    advance = 12 * int(np.count_nonzero(tail == VECT_12)) + 8 * int(np.count_nonzero(tail == VECT_8))
    if len(bases):
        state[5] = (w[bases[-1]] & 0x7FF) + advance
        state[6] = (w[bases[-1]] >> 11) & 1
    elif state[5] >= 0:
        state[5] += advance


def decode_numpy(words: np.ndarray, state: np.ndarray, counters: np.ndarray, width: int, height: int) -> tuple[EventArray, Triggers]:
    """What ``decode_numba`` gives for the same words and state, computed with whole-array operations."""
    typ = (words >> 12).astype(np.int8)
    w = words.astype(np.int64)
    have, t = _time_words(w, typ, state)
    y = _ffill_values(typ == ADDR_Y, w & 0x7FF, int(state[4]))
    is_x, is_vec = typ == ADDR_X, (typ == VECT_12) | (typ == VECT_8)

    # vector bases: the last VECT_BASE_X plus the advance of every vector word since
    vi = np.flatnonzero(is_vec)
    adv = np.where(typ[vi] == VECT_12, 12, 8)
    done = np.concatenate([[0], np.cumsum(adv)])  # advance of the vectors before each vector
    base_at = _ffill(typ == VECT_BASE_X)[vi]
    safe = np.maximum(base_at, 0)
    since = done[:-1] - done[np.searchsorted(vi, safe)]
    bx = np.where(base_at >= 0, (w[safe] & 0x7FF) + since, np.where(state[5] >= 0, state[5] + done[:-1], -1))
    bp = np.where(base_at >= 0, (w[safe] >> 11) & 1, state[6])

    no_base = np.zeros(len(w), bool)
    no_base[vi[bx < 0]] = True
    carries = (is_x | is_vec) & ~no_base
    no_time = carries & ~have
    no_y = carries & have & (y < 0)
    is_trig = typ == EXT_TRIGGER
    counters[0] += int(np.isin(typ, SKIPPED_TYPES).sum())
    counters[1] += int(np.isin(typ, (0x1, 0x9, 0xB, 0xC, 0xD)).sum())
    counters[2] += int(no_time.sum() + (is_trig & ~have).sum())
    counters[3] += int(no_y.sum())
    counters[4] += int(no_base.sum())

    good = carries & have & (y >= 0)
    # events in word order: an ADDR_X gives one, a vector one per set bit (lowest x first)
    vgood = good[vi]
    vrows = vi[vgood]
    vbits = np.where(typ[vrows] == VECT_12, w[vrows] & 0xFFF, w[vrows] & 0xFF).astype("<u2")
    unpacked = np.unpackbits(vbits.view(np.uint8).reshape(-1, 2), axis=1, bitorder="little")
    count = np.zeros(len(w), np.int64)
    count[good & is_x] = 1
    count[vrows] = unpacked.sum(axis=1)
    first = np.cumsum(count) - count
    total = int(count.sum())
    x = np.empty(total, np.int64)
    pol = np.empty(total, np.int64)
    src = np.empty(total, np.int64)
    xr = np.flatnonzero(good & is_x)
    at = first[xr]
    x[at], pol[at], src[at] = w[xr] & 0x7FF, (w[xr] >> 11) & 1, xr
    r, k = np.nonzero(unpacked)
    if len(r):
        vc = count[vrows]
        rank = np.arange(len(r)) - np.repeat(np.cumsum(vc) - vc, vc)
        at = first[vrows[r]] + rank
        x[at], pol[at], src[at] = bx[vgood][r] + k, bp[vgood][r], vrows[r]
    ey = y[src]
    inside = (x < width) & (ey < height)
    counters[5] += int(total - np.count_nonzero(inside))
    if not inside.all():
        x, ey, src, pol = x[inside], ey[inside], src[inside], pol[inside]
    events = EventArray(x, ey, t[src], np.where(pol == 1, 1, -1))

    trig = np.flatnonzero(is_trig & have)
    triggers = Triggers(t[trig], (w[trig] >> 8) & 0xF, w[trig] & 1)
    _advance_space(w, typ, state)
    return events, triggers


def skip_words(words: np.ndarray, state: np.ndarray) -> None:
    """Advance ``state`` over the uint16 ``words`` as decoding them would, producing nothing."""
    typ = (words >> 12).astype(np.int8)
    w = words.astype(np.int64)
    _time_words(w, typ, state)
    _advance_space(w, typ, state)


def state_time_us(state: np.ndarray) -> int | None:
    """The time in µs a decoder in ``state`` has reached (None before the first TIME_HIGH)."""
    return int((state[2] << 24) | (state[1] << 12) | state[3]) if state[0] else None
