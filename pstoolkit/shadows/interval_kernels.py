"""Compiled kernels of ``intervals``.

- ``run_counts``/``run_bounds`` (``intervals_from_grid``): the runs of True along the time axis of a
  (steps, P) map, in two passes over blocks of columns (one counting each column's runs, one writing
  them where the counts' running sum puts them), each reading the map row by row. numpy's version
  transposed the shadowed columns and took ``np.diff``: a second copy of the map and 3–4× the time.
- ``contains_on_grid``/``overlap_on_grid`` (``ShadowTable.contains_grid``/``shadowed_grid``): T
  times or windows for each of P pixels, each pixel's few table rows scanned for all its T queries.
  A ``searchsorted`` per query into a table of millions of keys misses the cache at every step.
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
def run_counts(shadowed: np.ndarray) -> np.ndarray:
    """(P,) int64: the runs of True in each column of ``shadowed`` (steps, P) uint8 (0 or 1)."""
    steps, p = shadowed.shape
    counts = np.zeros(p, dtype=np.int64)
    for block in prange((p + COLUMNS - 1) // COLUMNS):
        c0 = block * COLUMNS
        c1 = min(c0 + COLUMNS, p)
        for c in range(c0, c1):
            counts[c] = shadowed[0, c]
        # branch-free, so the column loop vectorises: a run starts where a 1 follows a 0
        for k in range(1, steps):
            for c in range(c0, c1):
                counts[c] += shadowed[k, c] & (1 - shadowed[k - 1, c])
    return counts


@numba.njit(cache=True, parallel=True, nogil=True)
def run_bounds(shadowed: np.ndarray, columns: np.ndarray, offsets: np.ndarray, first: np.ndarray,
               after: np.ndarray) -> None:
    """Each run of the columns ``columns`` (those with runs) of ``shadowed`` (steps, P) uint8 as
    [``first``, ``after``) bins, the runs of ``columns[i]`` in time order from ``offsets[i]``."""
    steps = shadowed.shape[0]
    n = columns.size
    for block in prange((n + COLUMNS - 1) // COLUMNS):
        i0 = block * COLUMNS
        i1 = min(i0 + COLUMNS, n)
        slot = offsets[i0:i1].copy()
        previous = np.zeros(i1 - i0, dtype=np.uint8)
        for k in range(steps):
            for i in range(i0, i1):
                now = shadowed[k, columns[i]]
                before = previous[i - i0]
                if now != before:
                    if now:
                        first[slot[i - i0]] = k
                    else:
                        after[slot[i - i0]] = k
                        slot[i - i0] += 1
                    previous[i - i0] = now
        for i in range(i0, i1):
            if previous[i - i0]:
                after[slot[i - i0]] = steps


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
