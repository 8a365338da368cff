"""Compiled kernels of ``intervals``.

- ``run_closures``/``close_runs`` (``intervals.RunCollector``): the runs of True along the time axis
  of a (steps, P) map fed a block of rows at a time, in two passes over blocks of columns (one
  counting the runs each column closes, one writing them where the counts' running sum puts them),
  each reading the block row by row, each column's open run carried to the next block. numpy's
  version transposed the shadowed columns of the whole map and took ``np.diff``: a second copy of the
  map and 3–4× the time; fed by blocks, the map itself need never exist.
- ``contains_on_grid``/``overlap_on_grid`` (``ShadowTable.contains_grid``/``shadowed_grid``): T
  times or windows for each of P pixels, each pixel's few table rows scanned for all its T queries.
  A ``searchsorted`` per query into a table of millions of keys misses the cache at every step.
- ``sorted_slots`` (``intervals.search_sorted``): ``numpy.searchsorted`` in parallel over the queries,
  the same indices: a table of millions of keys misses the cache at every step of every search, and
  numpy searches on one core.
- ``fill_runs`` (``rasterize``): each pixel's runs written into its column, pixels in parallel; the
  ±1 table of the runs' bounds and its running sum before took an int32 (steps + 1, P) table (0.76 GB
  at 512² event pixels and 720 steps) and longer.
"""

from __future__ import annotations

import numba
import numpy as np
from numba import prange

# Columns a thread takes at once: a row's share of them is a few cache lines.
COLUMNS = 256


@numba.njit(cache=True, parallel=True, nogil=True)
def run_closures(block: np.ndarray, previous: np.ndarray) -> np.ndarray:
    """(P,) int64: the runs of True that end inside ``block`` (n, P) uint8 (0 or 1), a 1 followed by
    a 0, ``previous`` (P,) the row before it."""
    n, p = block.shape
    counts = np.zeros(p, dtype=np.int64)
    for part in prange((p + COLUMNS - 1) // COLUMNS):
        c0 = part * COLUMNS
        c1 = min(c0 + COLUMNS, p)
        for c in range(c0, c1):
            counts[c] = previous[c] & (1 - block[0, c])
        # branch-free, so the column loop vectorises
        for k in range(1, n):
            for c in range(c0, c1):
                counts[c] += block[k - 1, c] & (1 - block[k, c])
    return counts


@numba.njit(cache=True, parallel=True, nogil=True)
def close_runs(block: np.ndarray, row0: int, previous: np.ndarray, open_at: np.ndarray, offsets: np.ndarray,
               column: np.ndarray, first: np.ndarray, after: np.ndarray) -> None:
    """Walk ``block`` (n, P) uint8, rows ``row0``…: a run opening notes its row in ``open_at`` (P,), a
    run ending writes (``column``, ``first``, ``after``) at its column's next slot from ``offsets``
    (the running sum of ``run_closures``); ``previous`` (P,) carries each column's last value on."""
    n, p = block.shape
    for part in prange((p + COLUMNS - 1) // COLUMNS):
        c0 = part * COLUMNS
        c1 = min(c0 + COLUMNS, p)
        slot = offsets[c0:c1].copy()
        for k in range(n):
            for c in range(c0, c1):
                now = block[k, c]
                if now != previous[c]:
                    if now:
                        open_at[c] = row0 + k
                    else:
                        column[slot[c - c0]] = c
                        first[slot[c - c0]] = open_at[c]
                        after[slot[c - c0]] = row0 + k
                        slot[c - c0] += 1
                    previous[c] = now


@numba.njit(cache=True, parallel=True, nogil=True)
def contains_on_grid(start: np.ndarray, end: np.ndarray, lo: np.ndarray, hi: np.ndarray, base: np.ndarray,
                     phase: np.ndarray, out: np.ndarray) -> None:
    """``out[t, i]``: whether key ``base[i] + phase[t]`` lies in one of the closed intervals
    ``start[lo[i]:hi[i]]``..``end[…]`` (the table rows of query i's pixel)."""
    for i in prange(lo.size):
        for t in range(phase.size):
            key = base[i] + phase[t]
            inside = False
            for r in range(lo[i], hi[i]):
                if start[r] <= key <= end[r]:
                    inside = True
                    break
            out[t, i] = inside


@numba.njit(cache=True, parallel=True, nogil=True)
def overlap_on_grid(start: np.ndarray, end: np.ndarray, lo: np.ndarray, hi: np.ndarray, base: np.ndarray,
                    a: np.ndarray, b: np.ndarray, period: float, out: np.ndarray) -> None:
    """``out[t, i]``: the length of [``a[t]``, ``b[t]``] (phases, 0 ≤ a < period, a ≤ b ≤ a + period;
    past the period it wraps to 0) inside the intervals ``start[lo[i]:hi[i]]``..``end[…]`` of query
    i's pixel, keys offset by ``base[i]``."""
    for i in prange(lo.size):
        for t in range(a.size):
            total = 0.0
            x0, x1 = base[i] + a[t], base[i] + min(b[t], period)
            w0, w1 = base[i], base[i] + max(b[t] - period, 0.0)
            for r in range(lo[i], hi[i]):
                total += max(0.0, min(x1, end[r]) - max(x0, start[r]))
                if b[t] > period:
                    total += max(0.0, min(w1, end[r]) - max(w0, start[r]))
            out[t, i] = total


@numba.njit(cache=True, parallel=True, nogil=True)
def fill_runs(out: np.ndarray, first: np.ndarray, last: np.ndarray, wraps: np.ndarray, owners: np.ndarray,
              groups: np.ndarray) -> None:
    """Set ``out[first[r]..last[r], owners[r]]`` (bins clipped to the table) for every run r, or for
    a run that ``wraps`` bins ``first[r]..`` to the end and ``..last[r]`` from the start; the runs come
    in ``groups`` (G + 1,) bounds of one owner each, which a thread takes whole, so no two threads
    write one column."""
    steps = out.shape[0]
    for g in prange(groups.size - 1):
        for r in range(groups[g], groups[g + 1]):
            if wraps[r]:
                for k in range(max(first[r], 0), steps):
                    out[k, owners[r]] = True
                for k in range(0, min(last[r], steps - 1) + 1):
                    out[k, owners[r]] = True
            else:
                for k in range(max(first[r], 0), min(last[r], steps - 1) + 1):
                    out[k, owners[r]] = True


@numba.njit(cache=True, parallel=True, nogil=True)
def sorted_slots(keys: np.ndarray, values: np.ndarray, right: bool, out: np.ndarray) -> None:
    """``out[i]``: ``numpy.searchsorted(keys, values[i], side="right" if right else "left")`` for
    increasing ``keys`` (K,) and ``values`` (N,) float64."""
    if right:
        for i in prange(values.size):
            out[i] = np.searchsorted(keys, values[i], side="right")
    else:
        for i in prange(values.size):
            out[i] = np.searchsorted(keys, values[i], side="left")
