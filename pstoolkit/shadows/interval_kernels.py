"""Compiled kernels of ``intervals``.

- ``run_counts``/``run_bounds`` (``intervals_from_grid``): the runs of True along the time axis of a
  (steps, P) map, in two passes over blocks of columns (one counting each column's runs, one writing
  them where the counts' running sum puts them), each reading the map row by row. numpy's version
  transposed the shadowed columns and took ``np.diff``: a second copy of the map and 3–4× the time.
- ``contains_on_grid``/``overlap_on_grid`` (``ShadowTable.contains_grid``/``shadowed_grid``): T
  times or windows for each of P pixels, each pixel's few table rows scanned for all its T queries.
  A ``searchsorted`` per query into a table of millions of keys misses the cache at every step.
- ``mark_bounds``/``covered`` (``rasterize``): the runs' bounds as ±1 in a (steps + 1, P) table, then
  its running sum over time by blocks of columns (``np.add.at`` and a row-by-row ``+=`` before).
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


@numba.njit(cache=True, nogil=True)
def mark_bounds(change: np.ndarray, starts: np.ndarray, stops: np.ndarray, owners: np.ndarray) -> None:
    """+1 at each run's first bin and −1 after its last in ``change`` (steps + 1, P) int32, bins
    clipped to [0, steps]; runs with ``stops`` < ``starts`` are skipped."""
    steps = change.shape[0] - 1
    for r in range(starts.size):
        if stops[r] < starts[r]:
            continue
        change[min(max(starts[r], 0), steps), owners[r]] += 1
        change[min(max(stops[r] + 1, 0), steps), owners[r]] -= 1


@numba.njit(cache=True, parallel=True, nogil=True)
def covered(change: np.ndarray, out: np.ndarray) -> None:
    """``out`` (steps, P) bool: the running sum of ``change`` (steps + 1, P) over time is positive."""
    steps, p = out.shape
    for block in prange((p + COLUMNS - 1) // COLUMNS):
        c0 = block * COLUMNS
        c1 = min(c0 + COLUMNS, p)
        running = np.zeros(c1 - c0, dtype=np.int64)
        for k in range(steps):
            for c in range(c0, c1):
                running[c - c0] += change[k, c]
                out[k, c] = running[c - c0] > 0
