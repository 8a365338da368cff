"""Prophesee EVT 3.0: decoding RAW files into event streams and encoding streams back, bit-exactly.

Words are 16-bit little-endian with the type in bits 15..12 (see ``docs/event-files.md``). The
decoder keeps the vendor's production semantics: a TIME_HIGH equal to the previous one keeps the
low bits, a changed one resets them; a wrap of the 24-bit time is counted when the new TIME_HIGH is
at least 2048 below the previous one, so a small backward TIME_LOW or TIME_HIGH step is taken as it
is, not as a wrap; vectors add their set bits to the current VECT_BASE_X, which then advances by
12 or 8. Words that carry no event are skipped and counted in ``DecodeStats``, never guessed at.

Two engines give identical results: a compiled loop (numba, when installed; ``PSFMT_NUMBA=0``
turns it off) and a vectorised numpy path that needs nothing beyond numpy; ``engine="auto"`` takes
the compiled one when it is there. The encoder writes TIME_HIGH/TIME_LOW/ADDR_Y only when they
change and runs of at least ``VECTOR_MIN_EVENTS`` events of one row, time and polarity within 32
pixels as a VECT_BASE_X followed by the triplet VECT_12, VECT_12, VECT_8 that the vendor's decoder
expects; both engines write the same bytes, whatever the block boundaries.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from psfmt.atomic import atomic_path
from psfmt.errors import FormatError
from psfmt.events import EventArray, Triggers
from psfmt.rawheader import (
    DecodeStats,
    concat_triggers,
    format_header,
    iter_words,
    read_sized_header,
)

try:  # the compiled fast path is optional: psfmt must work with numpy and h5py alone
    import numba
except ImportError:  # pragma: no cover - exercised where numba is absent
    numba = None

ADDR_Y, ADDR_X, VECT_BASE_X, VECT_12, VECT_8, TIME_LOW, TIME_HIGH, EXT_TRIGGER = 0x0, 0x2, 0x3, 0x4, 0x5, 0x6, 0x8, 0xA
SKIPPED_TYPES = (0x7, 0xE, 0xF)  # CONTINUED_4, OTHERS, CONTINUED_12: defined, carry no CD event
WRAP_US = 1 << 24
WRAP_DROP = 2048  # a TIME_HIGH this far below the previous one is a wrap, a smaller drop a step back
VECTOR_MIN_EVENTS = 5  # a base and a triplet cost 4 words: vectors pay from 5 events on
MAX_COORD = 2047
DEFAULT_CHUNK_WORDS = 1 << 22

# decoder state: have_high, high, wraps, low, y (-1: none yet), base_x (-1: none yet), base_p
_INITIAL_STATE = (0, 0, 0, 0, -1, -1, 0)
ENGINES = ("auto", "numba", "numpy")


def has_numba() -> bool:
    """Whether the compiled engine can run (numba installed and not disabled by PSFMT_NUMBA=0)."""
    return numba is not None and os.environ.get("PSFMT_NUMBA", "1") != "0"


def _engine(engine: str) -> str:
    if engine not in ENGINES:
        raise ValueError(f"engine must be one of {', '.join(ENGINES)}, not {engine!r}")
    if engine == "numba" and not has_numba():
        raise ValueError("engine 'numba' asked for but numba is not installed (or PSFMT_NUMBA=0)")
    return ("numba" if has_numba() else "numpy") if engine == "auto" else engine


def _jit(fn: Callable[..., Any]) -> Callable[..., Any]:
    return numba.njit(cache=True, nogil=True)(fn) if numba is not None else fn


# --- decoding: the compiled loop --------------------------------------------------------------------
def _decode_loop(words, state, counters, width, height, ox, oy, ot, op, tt, tc, tv):  # type: ignore[no-untyped-def]
    """Decode ``words`` from ``state`` into the output arrays until the words or the room run out;
    returns (events written, triggers written, words consumed) and updates ``state`` and ``counters``
    (others, unknown, no_time, no_y, no_base, outside)."""
    have_high, high, wraps, low, y, bx, bp = state[0], state[1], state[2], state[3], state[4], state[5], state[6]
    cap, tcap = ox.shape[0], tt.shape[0]
    n = 0
    m = 0
    i = 0
    while i < words.shape[0]:
        if n + 12 > cap or m >= tcap:
            break
        w = np.int64(words[i])
        typ = w >> 12
        if typ == ADDR_Y:
            y = w & 0x7FF
        elif typ == ADDR_X:
            if have_high == 0:
                counters[2] += 1
            elif y < 0:
                counters[3] += 1
            else:
                x = w & 0x7FF
                if x >= width or y >= height:
                    counters[5] += 1
                else:
                    ox[n] = x
                    oy[n] = y
                    ot[n] = (wraps << 24) | (high << 12) | low
                    op[n] = 1 if (w >> 11) & 1 else -1
                    n += 1
        elif typ == VECT_BASE_X:
            bx = w & 0x7FF
            bp = (w >> 11) & 1
        elif typ == VECT_12 or typ == VECT_8:
            nbits = 12 if typ == VECT_12 else 8
            if bx < 0:
                counters[4] += 1
            else:
                if have_high == 0:
                    counters[2] += 1
                elif y < 0:
                    counters[3] += 1
                else:
                    t = (wraps << 24) | (high << 12) | low
                    pol = 1 if bp else -1
                    for k in range(nbits):
                        if (w >> k) & 1:
                            x = bx + k
                            if x >= width or y >= height:
                                counters[5] += 1
                            else:
                                ox[n] = x
                                oy[n] = y
                                ot[n] = t
                                op[n] = pol
                                n += 1
                bx += nbits
        elif typ == TIME_LOW:
            low = w & 0xFFF
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
        elif typ == EXT_TRIGGER:
            if have_high == 0:
                counters[2] += 1
            else:
                tt[m] = (wraps << 24) | (high << 12) | low
                tc[m] = (w >> 8) & 0xF
                tv[m] = w & 1
                m += 1
        elif typ == 0x7 or typ == 0xE or typ == 0xF:
            counters[0] += 1
        else:
            counters[1] += 1
        i += 1
    state[0], state[1], state[2], state[3], state[4], state[5], state[6] = have_high, high, wraps, low, y, bx, bp
    return n, m, i


_decode_loop_jit = _jit(_decode_loop)


def _decode_numba(words: np.ndarray, state: np.ndarray, counters: np.ndarray, width: int, height: int) -> tuple[EventArray, Triggers]:
    parts: list[EventArray] = []
    trig: list[Triggers] = []
    cap = max(12, min(12 * len(words), 1 << 23))
    start = 0
    while start < len(words):
        ox, oy = np.empty(cap, np.uint16), np.empty(cap, np.uint16)
        ot, op = np.empty(cap, np.int64), np.empty(cap, np.int8)
        tt, tc, tv = np.empty(1 << 16, np.int64), np.empty(1 << 16, np.uint8), np.empty(1 << 16, np.int8)
        n, m, used = _decode_loop_jit(words[start:], state, counters, width, height, ox, oy, ot, op, tt, tc, tv)
        parts.append(EventArray(ox[:n], oy[:n], ot[:n], op[:n]))
        trig.append(Triggers(tt[:m], tc[:m], tv[:m]))
        start += used
    if not parts:
        return EventArray.empty(), concat_triggers([])
    if len(parts) == 1:
        return parts[0], trig[0]
    return EventArray.concatenate(parts), concat_triggers(trig)


# --- decoding: the vectorised numpy path ------------------------------------------------------------
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


def _decode_numpy(words: np.ndarray, state: np.ndarray, counters: np.ndarray, width: int, height: int) -> tuple[EventArray, Triggers]:
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


@dataclass
class Decoder:
    """A streaming EVT 3.0 decoder: feed word blocks in order, get events and triggers per block.

    ``width``/``height`` bound the accepted coordinates (events outside are dropped and counted).
    """

    width: int = MAX_COORD + 1
    height: int = MAX_COORD + 1
    engine: str = "auto"
    stats: DecodeStats = field(default_factory=DecodeStats)

    def __post_init__(self) -> None:
        self.engine = _engine(self.engine)
        self.state = np.array(_INITIAL_STATE, dtype=np.int64)

    def feed(self, words: np.ndarray) -> tuple[EventArray, Triggers]:
        counters = np.zeros(6, np.int64)
        decode = _decode_numba if self.engine == "numba" else _decode_numpy
        events, triggers = decode(np.asarray(words, dtype=np.uint16), self.state, counters, self.width, self.height)
        self.stats.add_counters(counters)
        self.stats.events += len(events)
        self.stats.triggers += len(triggers)
        return events, triggers

    @property
    def time_us(self) -> int | None:
        """The time the stream has reached (None before the first TIME_HIGH)."""
        s = self.state
        return int((s[2] << 24) | (s[1] << 12) | s[3]) if s[0] else None

    def skip(self, words: np.ndarray) -> None:
        """Advance the state over ``words`` without producing events (for time windows)."""
        words = np.asarray(words, dtype=np.uint16)
        typ = (words >> 12).astype(np.int8)
        w = words.astype(np.int64)
        _time_words(w, typ, self.state)
        _advance_space(w, typ, self.state)


def decode(
    data: bytes | np.ndarray, width: int = MAX_COORD + 1, height: int = MAX_COORD + 1, *, engine: str = "auto"
) -> tuple[EventArray, Triggers, DecodeStats]:
    """Decode EVT 3.0 words (bytes without header, or a uint16 array) in one go."""
    words = np.frombuffer(data, dtype="<u2", count=len(data) // 2) if isinstance(data, (bytes, bytearray, memoryview)) else data
    decoder = Decoder(width, height, engine)
    decoder.stats.words = len(words)
    events, triggers = decoder.feed(words)
    return events, triggers, decoder.stats


class Evt3File:
    """An EVT 3.0 RAW file, decoded in bounded memory: ``chunks()`` streams it, ``window()`` decodes
    only the words around a time range, ``read()`` decodes everything; ``stats`` sums up the last pass."""

    def __init__(self, path: str | os.PathLike[str], *, engine: str = "auto", chunk_words: int = DEFAULT_CHUNK_WORDS) -> None:
        self.path = Path(path)
        self.header, self.width, self.height = read_sized_header(self.path, "EVT3", "EVT 3.0")
        self.engine = _engine(engine)
        self.chunk_words = int(chunk_words)
        self.stats = DecodeStats()

    def _decoder(self) -> Decoder:
        self.stats = DecodeStats()
        return Decoder(self.width, self.height, self.engine, self.stats)

    def chunks(self) -> Iterator[tuple[EventArray, Triggers]]:
        """(events, triggers) per block of ``chunk_words`` words, in file order."""
        decoder = self._decoder()
        for _, words in iter_words(self.path, self.header, "<u2", self.chunk_words, self.stats):
            yield decoder.feed(words)

    def read(self) -> tuple[EventArray, Triggers]:
        parts = list(self.chunks())
        return EventArray.concatenate([e for e, _ in parts]), concat_triggers([t for _, t in parts])

    def window(self, t0_us: int, t1_us: int) -> EventArray:
        """Events with ``t0_us <= t < t1_us``. Blocks that end before the window only advance the
        decoder state and reading stops once the stream is past the window, assuming (as every
        sensor writes them) that times never step back by more than one TIME_HIGH period (4096 µs)."""
        decoder = self._decoder()
        slack = 1 << 12
        parts = []
        for _, words in iter_words(self.path, self.header, "<u2", self.chunk_words, self.stats):
            probe = decoder.state.copy()
            decoder.skip(words)
            end = decoder.time_us
            if end is None or end < t0_us - slack:
                continue
            decoder.state[:] = probe
            events, _ = decoder.feed(words)
            keep = (events.t >= t0_us) & (events.t < t1_us)
            parts.append(events[keep])
            if end >= t1_us + slack:
                break
        return EventArray.concatenate(parts)


# --- encoding ---------------------------------------------------------------------------------------
def _encode_loop(x, y, t, p, out, state):  # type: ignore[no-untyped-def]
    """Encode sorted events into ``out`` from ``state`` (abs_high: t >> 12 or -1, low, y or -1);
    returns the number of words written."""
    cur, low, cy = state[0], state[1], state[2]
    n = x.shape[0]
    k = 0
    i = 0
    while i < n:
        ti = t[i]
        ta = ti >> 12
        if cur < 0:
            cur = ta if ta < 4096 else 0
            out[k] = (TIME_HIGH << 12) | (cur & 0xFFF)
            k += 1
            low = 0
        while (ta >> 12) > (cur >> 12):
            # wrap through 0xFFF → 0: a full-range drop that every decoder reads as one wrap
            if (cur & 0xFFF) != 0xFFF:
                out[k] = (TIME_HIGH << 12) | 0xFFF
                k += 1
            out[k] = TIME_HIGH << 12
            k += 1
            cur = ((cur >> 12) + 1) << 12
            low = 0
        if ta != cur:
            out[k] = (TIME_HIGH << 12) | (ta & 0xFFF)
            k += 1
            cur = ta
            low = 0
        if (ti & 0xFFF) != low:
            low = ti & 0xFFF
            out[k] = (TIME_LOW << 12) | low
            k += 1
        yi = np.int64(y[i])
        if yi != cy:
            cy = yi
            out[k] = (ADDR_Y << 12) | yi
            k += 1
        pol = 1 if p[i] > 0 else 0
        x0 = np.int64(x[i])
        j = i + 1
        while j < n and t[j] == ti and y[j] == y[i] and (p[j] > 0) == (pol == 1) and x[j] > x[j - 1] and np.int64(x[j]) < x0 + 32:
            j += 1
        if j - i >= VECTOR_MIN_EVENTS:
            bits = np.int64(0)
            for q in range(i, j):
                bits |= np.int64(1) << (np.int64(x[q]) - x0)
            out[k] = (VECT_BASE_X << 12) | (pol << 11) | x0
            out[k + 1] = (VECT_12 << 12) | (bits & 0xFFF)
            out[k + 2] = (VECT_12 << 12) | ((bits >> 12) & 0xFFF)
            out[k + 3] = (VECT_8 << 12) | ((bits >> 24) & 0xFF)
            k += 4
        else:
            for q in range(i, j):
                out[k] = (ADDR_X << 12) | (pol << 11) | np.int64(x[q])
                k += 1
        i = j
    state[0], state[1], state[2] = cur, low, cy
    return k


_encode_loop_jit = _jit(_encode_loop)


def _windows(x: np.ndarray, y: np.ndarray, t: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """Starts of the encoder's runs: maximal stretches of one time, row and polarity with rising x,
    cut greedily into 32-pixel windows from each stretch's first event (as ``_encode_loop`` does)."""
    n = len(t)
    cut = np.ones(n, bool)
    cut[1:] = (t[1:] != t[:-1]) | (y[1:] != y[:-1]) | (pos[1:] != pos[:-1]) | (x[1:] <= x[:-1])
    first = np.flatnonzero(cut)
    end = np.append(first[1:], n)
    long = (end - first > 1) & (x[end - 1] - x[first] >= 32)
    is_start = cut.copy()
    if long.any():
        # only stretches wider than one window need more cuts; their keys rise through the block
        key = (np.cumsum(cut) - 1) * 4096 + x
        active, active_end = first[long], end[long]
        while len(active):
            nxt = np.searchsorted(key, key[active] + 32, side="left")
            more = nxt < active_end
            active, active_end = nxt[more], active_end[more]
            is_start[active] = True
    return np.flatnonzero(is_start)


def _time_words_for(prev_cur: int, prev_low: int, ta: int) -> tuple[list[int], int]:
    """The TIME_HIGH words ``_encode_loop`` writes to move from ``prev_cur`` to ``ta`` (with wraps) and
    the low bits in force afterwards."""
    words: list[int] = []
    cur, low = prev_cur, prev_low
    if cur < 0:
        cur = ta if ta < 4096 else 0
        words.append((TIME_HIGH << 12) | (cur & 0xFFF))
        low = 0
    while (ta >> 12) > (cur >> 12):
        if (cur & 0xFFF) != 0xFFF:
            words.append((TIME_HIGH << 12) | 0xFFF)
        words.append(TIME_HIGH << 12)
        cur = ((cur >> 12) + 1) << 12
        low = 0
    if ta != cur:
        words.append((TIME_HIGH << 12) | (ta & 0xFFF))
        low = 0
    return words, low


def _encode_numpy(x: np.ndarray, y: np.ndarray, t: np.ndarray, p: np.ndarray, state: np.ndarray) -> np.ndarray:
    """The words of ``_encode_loop``, computed with whole-array operations; updates ``state``."""
    xi, yi, pos = x.astype(np.int64), y.astype(np.int64), p > 0
    ws = _windows(xi, yi, t, pos)
    count = np.diff(np.append(ws, len(t)))
    vec = count >= VECTOR_MIN_EVENTS
    tw, yw, pw = t[ws], yi[ws], pos[ws].astype(np.int64)
    ta, tl = tw >> 12, tw & 0xFFF
    prev_cur = np.concatenate([[state[0]], ta[:-1]])
    prev_low = np.concatenate([[state[1]], tl[:-1]])
    prev_y = np.concatenate([[state[2]], yw[:-1]])
    # the first window and those crossing a wrap get their TIME_HIGH words one by one (few of them)
    special = np.flatnonzero((prev_cur < 0) | ((ta >> 12) > (prev_cur >> 12)))
    n_th = (ta != prev_cur).astype(np.int64)
    low_before = np.where(n_th > 0, 0, prev_low)
    special_words = {}
    for w in special:
        words, low_before[w] = _time_words_for(int(prev_cur[w]), int(prev_low[w]), int(ta[w]))
        n_th[w] = len(words)
        special_words[w] = words
    has_tl = tl != low_before
    has_y = yw != prev_y
    n_body = np.where(vec, 4, count)
    size = n_th + has_tl + has_y + n_body
    off = np.cumsum(size) - size
    out = np.empty(int(size.sum()), dtype=np.uint16)
    plain = np.flatnonzero(n_th == 1)
    plain = plain[~np.isin(plain, special)]
    out[off[plain]] = (TIME_HIGH << 12) | (ta[plain] & 0xFFF)
    for w, words in special_words.items():
        out[off[w] : off[w] + len(words)] = words
    at = off + n_th
    out[at[has_tl]] = (TIME_LOW << 12) | tl[has_tl]
    at = at + has_tl
    out[at[has_y]] = (ADDR_Y << 12) | yw[has_y]
    body = at + has_y
    # vectors: one 32-bit mask per window, relative to its first x
    window_of = np.repeat(np.arange(len(ws)), count)
    bits = np.bitwise_or.reduceat(np.where(vec[window_of], np.int64(1) << np.minimum(xi - xi[ws][window_of], 62), 0), ws)
    v = np.flatnonzero(vec)
    out[body[v]] = (VECT_BASE_X << 12) | (pw[v] << 11) | xi[ws[v]]
    out[body[v] + 1] = (VECT_12 << 12) | (bits[v] & 0xFFF)
    out[body[v] + 2] = (VECT_12 << 12) | ((bits[v] >> 12) & 0xFFF)
    out[body[v] + 3] = (VECT_8 << 12) | ((bits[v] >> 24) & 0xFF)
    single = ~vec[window_of]
    ev = np.flatnonzero(single)
    wid = window_of[ev]
    out[body[wid] + ev - ws[wid]] = (ADDR_X << 12) | (pos[ev].astype(np.int64) << 11) | xi[ev]
    state[0], state[1], state[2] = ta[-1], tl[-1], yw[-1]
    return out


def _check_encodable(events: EventArray, last_t_us: int | None) -> None:
    if len(events) == 0:
        return
    if int(events.t[0]) < 0:
        raise ValueError(f"EVT 3.0 cannot hold negative times (first event at {int(events.t[0])} µs)")
    if not events.is_sorted() or (last_t_us is not None and int(events.t[0]) < last_t_us):
        raise ValueError("EVT 3.0 encoding needs events sorted by time")
    if int(events.x.max()) > MAX_COORD or int(events.y.max()) > MAX_COORD:
        raise ValueError(f"EVT 3.0 coordinates are 11-bit: x and y must be at most {MAX_COORD}")


class Encoder:
    """A streaming EVT 3.0 encoder: ``feed`` sorted event blocks in order, ``finish`` at the end.

    Events sharing the last time of a block are held back until the next block, so the bytes do not
    depend on how the stream was cut into blocks."""

    def __init__(self, engine: str = "auto") -> None:
        self.engine = _engine(engine)
        self.state = np.array([-1, 0, -1], dtype=np.int64)
        self._held = EventArray.empty()
        self._last: int | None = None

    def _encode(self, events: EventArray) -> bytes:
        if len(events) == 0:
            return b""
        if self.engine == "numpy":
            return _encode_numpy(events.x, events.y, events.t, events.p, self.state).astype("<u2").tobytes()
        epochs = int(events.t[-1] >> 24) - max(0, int(self.state[0]) >> 12) + 1
        out = np.empty(4 * len(events) + 2 * epochs + 4, dtype=np.uint16)
        k = _encode_loop_jit(events.x, events.y, events.t, events.p, out, self.state)
        return out[:k].astype("<u2").tobytes()

    def feed(self, events: EventArray) -> bytes:
        _check_encodable(events, self._last)
        if len(events) == 0:
            return b""
        self._last = int(events.t[-1])
        block = EventArray.concatenate([self._held, events]) if len(self._held) else events
        cut = int(np.searchsorted(block.t, block.t[-1], side="left"))
        self._held = block[cut:]
        return self._encode(block[:cut])

    def finish(self) -> bytes:
        held, self._held = self._held, EventArray.empty()
        return self._encode(held)


def encode(events: EventArray, *, engine: str = "auto") -> bytes:
    """EVT 3.0 words (no header) for sorted events; ``decode(encode(e))`` gives ``e`` back exactly."""
    encoder = Encoder(engine)
    return encoder.feed(events) + encoder.finish()


def encoded_size(chunks: Iterable[EventArray], *, engine: str = "auto") -> int:
    """Bytes of the EVT 3.0 encoding of a stream given block by block (header not counted)."""
    encoder = Encoder(engine)
    return sum(len(encoder.feed(c)) for c in chunks) + len(encoder.finish())


def write_raw(
    path: str | os.PathLike[str],
    chunks: Iterable[EventArray],
    width: int,
    height: int,
    *,
    header: dict[str, str] | None = None,
    engine: str = "auto",
) -> Path:
    """Write an EVT 3.0 RAW file (header and words) from sorted event blocks, atomically."""
    path = Path(path)
    if width > MAX_COORD + 1 or height > MAX_COORD + 1:
        raise FormatError(path, f"EVT 3.0 holds sensors up to {MAX_COORD + 1}×{MAX_COORD + 1}, not {width}×{height}")
    encoder = Encoder(engine)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(format_header("EVT3", width, height, header))
        for block in chunks:
            fh.write(encoder.feed(block))
        fh.write(encoder.finish())
    return path
