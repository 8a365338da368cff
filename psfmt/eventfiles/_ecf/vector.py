"""The ECF decoder with whole-array numpy operations: what ``psfmt.eventfiles._ecf.loop`` gives, without numba.

Only the escapes are walked one by one: a count escape (a time byte ``d << 4 | 15``, a row word
``y << 5 | 31``, a polarity byte ``p << 7 | 127``) makes the next bytes a count rather than a code.
The first candidate at or after a code boundary is always a real escape (nothing before it in the
stretch could have swallowed it), so one pass over the candidates finds them all; everything else
is vectorised.
"""

from __future__ import annotations

import numpy as np

from psfmt.eventfiles._ecf.chunk import LONG_DELTA, MAX_DIGITS, MODE_PACKED, MODE_PACKED_XP, OK, OUTSIDE, OVERRUN, SHORT, TIME_BACK


class ChunkFault(Exception):
    """A chunk that cannot be decoded; ``code`` is a status of ``psfmt.eventfiles._ecf.chunk``."""

    def __init__(self, code: int) -> None:
        super().__init__(code)
        self.code = code


def _escapes(candidates: np.ndarray, width: int) -> np.ndarray:
    """Positions of the real escapes among ``candidates`` (sorted code positions whose code is an
    escape followed by ``width`` count positions)."""
    real = []
    boundary = 0
    for c in candidates.tolist():
        if c >= boundary:
            real.append(c)
            boundary = c + 1 + width
    return np.asarray(real, np.int64)


def _u16(data: np.ndarray, pos: int, count: int) -> np.ndarray:
    """``count`` u16 words from byte ``pos`` (any alignment); ChunkFault(SHORT) where they run out."""
    if pos + 2 * count > len(data):
        raise ChunkFault(SHORT)
    raw = data[pos : pos + 2 * count].astype(np.int64)
    return raw[0::2] | (raw[1::2] << 8)


def _cut(cum: np.ndarray, n: int, exact: bool = True) -> int:
    """Index of the run at which the cumulative counts ``cum`` reach ``n``."""
    end = int(np.searchsorted(cum, n))
    if end == len(cum):
        raise ChunkFault(SHORT)
    if exact and cum[end] != n:
        raise ChunkFault(OVERRUN)
    return end


def _times(data: np.ndarray, n: int) -> tuple[np.ndarray, int]:
    """The n times (int64 µs) and the byte position after them."""
    if len(data) < 12:
        raise ChunkFault(SHORT)
    origin = np.uint64(data[4:12].view("<u8")[0])
    size = len(data) - 12
    body = np.concatenate([data[12:], np.zeros(2, np.uint8)]).astype(np.int64)  # room for a cut-off count
    hi, lo = body >> 4, body & 15
    ext = _escapes(np.flatnonzero((hi[:size] != 15) & (lo[:size] == 15)), 2)
    is_code = np.ones(size, bool)
    counts_at = np.concatenate([ext + 1, ext + 2])
    is_code[counts_at[counts_at < size]] = False
    code_at = np.flatnonzero(is_code)
    final = hi[code_at] != 15
    ends = code_at[final]
    count = lo[ends]
    escaped = count == 15
    count[escaped] = body[ends[escaped] + 1] | (body[ends[escaped] + 2] << 8)
    last = _cut(np.cumsum(count), n)
    # the digits of each delta: escape nibbles (lo) then the final nibble (hi), least significant first
    groups = np.cumsum(final) - final
    used = groups <= last
    code_at, final, groups = code_at[used], final[used], groups[used]
    first = np.searchsorted(groups, np.arange(last + 1))
    rank = np.arange(len(groups)) - first[groups]
    digit = np.where(final, hi[code_at], lo[code_at])
    if (rank >= MAX_DIGITS + 1).any() or ((rank == MAX_DIGITS) & (digit != 0)).any():
        raise ChunkFault(LONG_DELTA)
    shift = np.minimum(rank, MAX_DIGITS - 1).astype(np.uint64) * np.uint64(4)
    parts = np.where(rank < MAX_DIGITS, digit.astype(np.uint64) << shift, np.uint64(0))
    delta = np.bitwise_or.reduceat(parts, first)
    with np.errstate(over="ignore"):
        stamps = (origin + np.cumsum(delta, dtype=np.uint64)).view(np.int64)
    if (np.diff(stamps) < 0).any() or stamps[0] < np.int64(origin):
        raise ChunkFault(TIME_BACK)
    stop = int(ends[last]) + 1 + (2 if lo[ends[last]] == 15 else 0)
    if stop > size:
        raise ChunkFault(SHORT)
    return np.repeat(stamps, count[: last + 1]), 12 + stop


def _rows(data: np.ndarray, pos: int, n: int) -> tuple[np.ndarray, int]:
    """The n rows and the byte position after them."""
    words = _u16(data, pos, (len(data) - pos) // 2)
    count = words & 31
    ext = _escapes(np.flatnonzero(count == 31), 1)
    code_at = np.setdiff1d(np.arange(len(words)), ext + 1, assume_unique=True)
    padded = np.append(words, 0)
    runs = np.where(count[code_at] == 31, padded[code_at + 1], count[code_at])
    last = _cut(np.cumsum(runs), n)
    stop = int(code_at[last]) + (2 if count[code_at[last]] == 31 else 1)
    if stop > len(words):
        raise ChunkFault(SHORT)
    return np.repeat(words[code_at[: last + 1]] >> 5, runs[: last + 1]), pos + 2 * stop


def _polarity_runs(data: np.ndarray, pos: int, n: int) -> np.ndarray:
    """The n polarities (0/1)."""
    body = np.concatenate([data[pos:], np.zeros(2, np.uint8)]).astype(np.int64)
    size = len(data) - pos
    count = body[:size] & 127
    ext = _escapes(np.flatnonzero(count == 127), 2)
    code_at = np.setdiff1d(np.arange(size), np.concatenate([ext + 1, ext + 2]), assume_unique=True)
    runs = np.where(count[code_at] == 127, body[code_at + 1] | (body[code_at + 2] << 8), count[code_at])
    last = _cut(np.cumsum(runs), n)
    if int(code_at[last]) + (3 if count[code_at[last]] == 127 else 1) > size:
        raise ChunkFault(SHORT)
    return np.repeat(body[code_at[: last + 1]] >> 7, runs[: last + 1])


def _masked_x(data: np.ndarray, pos: int, n: int) -> tuple[np.ndarray, int]:
    """The n columns and the byte position after them; mask bits past the n-th event are ignored."""
    words = _u16(data, pos, (len(data) - pos) // 2)
    present = np.ones((len(words), 6), bool)
    present[:, 1:] = (words[:, None] >> np.arange(4, -1, -1)) & 1 == 1
    last = _cut(np.cumsum(present.sum(axis=1)), n, exact=False)
    xs = ((words[: last + 1] >> 5)[:, None] + np.arange(6))[present[: last + 1]]
    return xs[:n], pos + 2 * (last + 1)


def _groups(data: np.ndarray, pos: int, n: int, word_bytes: int) -> np.ndarray:
    """The n values packed four to a group of three words of ``word_bytes`` bytes (each value
    three quarters of a word: 24 bits in u32 words, 12 bits in u16 words)."""
    groups = (n + 3) // 4
    if pos + 3 * word_bytes * groups > len(data):
        raise ChunkFault(SHORT)
    raw = data[pos : pos + 3 * word_bytes * groups].reshape(groups, 3, word_bytes).astype(np.int64)
    w0, w1, w2 = (sum(raw[:, j, k] << (8 * k) for k in range(word_bytes)) for j in range(3))
    u = 2 * word_bytes  # a quarter word, in bits
    out = np.empty((groups, 4), np.int64)
    out[:, 0] = w0 >> u
    out[:, 1] = (w0 & ((1 << u) - 1)) | ((w1 >> (2 * u)) << u)
    out[:, 2] = (w1 & ((1 << (2 * u)) - 1)) | ((w2 >> (3 * u)) << (2 * u))
    out[:, 3] = w2 & ((1 << (3 * u)) - 1)
    return out.reshape(-1)[:n]


def decode_chunk(data: np.ndarray, n: int, width: int, height: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """x, y (int64), t (int64 µs), p (±1) of the ``n`` events of one chunk's bytes (uint8);
    ChunkFault with the first fault's code otherwise."""
    mode = int(data[0]) & 3 if len(data) else 0
    t, pos = _times(data, n)
    if mode & MODE_PACKED:
        v = _groups(data, pos, n, 4)
        x, y, p = (v >> 1) & 0x7FF, (v >> 12) & 0x7FF, v & 1
    else:
        y, pos = _rows(data, pos, n)
        if mode & MODE_PACKED_XP:
            v = _groups(data, pos, n, 2)
            x, p = v >> 1, v & 1
        else:
            x, pos = _masked_x(data, pos, n)
            p = _polarity_runs(data, pos, n)
    if n and (int(x.max()) >= width or int(y.max()) >= height):
        raise ChunkFault(OUTSIDE)
    return x, y, t, 2 * p - 1


def decode_vector(buf, starts, ends, counts, at, width, height, x, y, t, p, status) -> None:  # type: ignore[no-untyped-def]
    """What ``psfmt.eventfiles._ecf.loop.decode_loop`` does, chunk by chunk with whole-array operations."""
    for k in range(len(starts)):
        n, o = int(counts[k]), int(at[k])
        try:
            cx, cy, ct, cp = decode_chunk(buf[starts[k] : ends[k]], n, width, height)
        except ChunkFault as fault:
            status[k] = fault.code
            continue
        x[o : o + n], y[o : o + n], t[o : o + n], p[o : o + n] = cx, cy, ct, cp
        status[k] = OK
