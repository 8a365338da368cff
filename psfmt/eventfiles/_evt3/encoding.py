"""The EVT 3.0 encoder's kernel: sorted event columns and a carried state in, words out.

The state is an int64 array laid out as ``ENCODER_STATE``. ``encode_loop`` is the reference (numba
compiles it for ``encode_numba``); ``encode_numpy`` writes the same words with whole-array
operations.
"""

from __future__ import annotations

import numpy as np

from psfmt.eventfiles._evt3.engine import jit
from psfmt.eventfiles._evt3.words import ADDR_X, ADDR_Y, TIME_HIGH, TIME_LOW, VECT_8, VECT_12, VECT_BASE_X, VECTOR_MIN_EVENTS

ENCODER_STATE = (-1, 0, -1)
"""The state before the first event: the TIME_HIGH in force as t >> 12 (-1: none yet), the low bits, y (-1: none yet)."""


def encode_loop(x, y, t, p, out, state):  # type: ignore[no-untyped-def]
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


_encode_loop_compiled = jit(encode_loop)


def encode_numba(x: np.ndarray, y: np.ndarray, t: np.ndarray, p: np.ndarray, state: np.ndarray) -> np.ndarray:
    """The uint16 words of the sorted events (columns ``x``, ``y``, ``t`` in µs, ``p``) by the compiled
    loop; updates ``state``."""
    # room for four words an event and the TIME_HIGH pair of every 2^24 µs wrap the block crosses
    epochs = int(t[-1] >> 24) - max(0, int(state[0]) >> 12) + 1
    out = np.empty(4 * len(t) + 2 * epochs + 4, dtype=np.uint16)
    k = _encode_loop_compiled(x, y, t, p, out, state)
    return out[:k]


def _windows(x: np.ndarray, y: np.ndarray, t: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """Starts of the encoder's runs: maximal stretches of one time, row and polarity with rising x,
    cut greedily into 32-pixel windows from each stretch's first event (as ``encode_loop`` does)."""
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
    """The TIME_HIGH words ``encode_loop`` writes to move from ``prev_cur`` to ``ta`` (with wraps) and
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


def encode_numpy(x: np.ndarray, y: np.ndarray, t: np.ndarray, p: np.ndarray, state: np.ndarray) -> np.ndarray:
    """The words of ``encode_loop``, computed with whole-array operations; updates ``state``."""
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
