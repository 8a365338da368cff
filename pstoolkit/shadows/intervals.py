"""Cast-shadow intervals of a periodic light and fast lookups in them.

A shadow is an interval of the light's phase (µs since a phase origin, in [0, period)) during which a
pixel is in a cast shadow; ``t1 < t0`` means it wraps past the period's end. ``ShadowIntervals`` is
a plain list of them; ``ShadowTable`` merges a list into disjoint, non-wrapping intervals keyed by
pixel·2·period + phase, and answers "is pixel x in shadow at phase t" and "how long is pixel x in
shadow between two phases" for many queries at once, each by one ``search_sorted``.
``intervals_from_grid`` turns a boolean map of a time grid into intervals (detectors that test
discrete light directions); ``rasterize`` does the opposite.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# Queries below this many take numpy's search: the compiled one's threads cost more than they save.
PARALLEL_SEARCH = 1 << 14


def search_sorted(keys: np.ndarray, values: np.ndarray, side: str = "left") -> np.ndarray:
    """``numpy.searchsorted(keys, values, side)`` for increasing float64 ``keys``, in parallel over the
    ``values`` (any shape) when they are many (``interval_kernels.sorted_slots``): the same indices."""
    values = np.asarray(values, dtype=np.float64)
    if values.size < PARALLEL_SEARCH:
        return np.searchsorted(keys, values, side=side)
    from pstoolkit.shadows.interval_kernels import sorted_slots  # deferred: numba

    out = np.empty(values.shape, dtype=np.int64)
    sorted_slots(np.ascontiguousarray(keys, dtype=np.float64), np.ascontiguousarray(values).ravel(), side == "right", out.ravel())
    return out


@dataclass
class ShadowIntervals:
    """Shadow intervals: flat ``pixel`` (S,) (event or frame pixel, as the producer says), phases
    ``t0_us``, ``t1_us`` (S,) in µs (float64); t1 < t0 wraps past the period's end, and t1 − t0 of a
    whole period or more covers all of it."""

    pixel: np.ndarray
    t0_us: np.ndarray
    t1_us: np.ndarray

    def __len__(self) -> int:
        return len(self.pixel)

    @classmethod
    def empty(cls) -> ShadowIntervals:
        return cls(np.empty(0, np.int64), np.empty(0), np.empty(0))

    @classmethod
    def concatenate(cls, parts: list[ShadowIntervals]) -> ShadowIntervals:
        if not parts:
            return cls.empty()
        return cls(*(np.concatenate([getattr(p, name) for p in parts]) for name in ("pixel", "t0_us", "t1_us")))


@dataclass
class ShadowTable:
    """Merged, non-wrapping shadow intervals keyed by pixel·2·period + phase, for vectorised lookups:
    ``start``/``end`` (S,) float64 keys, sorted, disjoint; closed intervals; ``before`` (S,) the total
    shadow time of all earlier intervals in key order. The stride of two periods keeps one pixel's
    interval ending at the period apart from the next pixel's at 0."""

    start: np.ndarray
    end: np.ndarray
    period_us: float
    before: np.ndarray
    _owners: np.ndarray | None = field(default=None, init=False, repr=False, compare=False)

    @classmethod
    def build(cls, shadows: ShadowIntervals, period_us: float) -> ShadowTable:
        period = float(period_us)
        t0, t1 = _phases(shadows, period)
        wraps = t1 < t0
        base = np.asarray(shadows.pixel, dtype=np.float64) * (2.0 * period)
        # a wrapping interval is split into [t0, period) and [0, t1]
        start = np.concatenate([base + t0, base[wraps]])
        end = np.concatenate([base + np.where(wraps, period, t1), base[wraps] + t1[wraps]])
        order = np.argsort(start, kind="stable")
        start, end = start[order], end[order]
        if start.size:
            # a pixel's keys lie in [2·pixel·period, (2·pixel+1)·period], so a running maximum of
            # the ends never reaches across pixels; a new group starts where an interval begins after it
            reach = np.maximum.accumulate(end)
            new = np.flatnonzero(np.r_[True, start[1:] > reach[:-1]])
            start, end = start[new], np.maximum.reduceat(end, new)
        lengths = end - start
        return cls(start=start, end=end, period_us=period, before=np.cumsum(lengths) - lengths)

    def __len__(self) -> int:
        return len(self.start)

    def _key(self, pixel: np.ndarray, phase_us: np.ndarray) -> np.ndarray:
        return np.asarray(pixel, dtype=np.int64).astype(np.float64) * (2.0 * self.period_us) + np.asarray(phase_us, dtype=np.float64)

    def _shadowed_at_all(self, pixel: np.ndarray) -> np.ndarray:
        """(N,) bool: whether ``pixel`` (N,) has any interval. Only those queries need a search: a
        binary search per query in a table of millions of keys misses the cache at every step, and
        most pixels are never shadowed."""
        if self._owners is None:
            owner = np.floor(self.start / (2.0 * self.period_us)).astype(np.int64)
            self._owners = np.zeros(int(owner.max()) + 1 if owner.size else 0, dtype=bool)
            self._owners[owner] = True
        pixel = np.asarray(pixel, dtype=np.int64)
        inside = (pixel >= 0) & (pixel < self._owners.size)
        return inside & self._owners[np.where(inside, pixel, 0)] if self._owners.size else np.zeros(pixel.shape, dtype=bool)

    def contains(self, pixel: np.ndarray, t_us: np.ndarray) -> np.ndarray:
        """(N,) bool: whether ``pixel`` (N,) is in shadow at phase ``t_us`` (N,) (any time; reduced
        modulo the period, so phase 0 is the phase origin the intervals were found in)."""
        pixel, t_us = np.broadcast_arrays(np.asarray(pixel, dtype=np.int64), np.asarray(t_us, dtype=np.float64))
        out = np.zeros(pixel.shape, dtype=bool)
        busy = self._shadowed_at_all(pixel)
        if busy.any():
            out[busy] = self._contains(pixel[busy], t_us[busy])
        return out

    def _contains(self, pixel: np.ndarray, t_us: np.ndarray) -> np.ndarray:
        """``contains`` by one search per query."""
        key = self._key(pixel, np.mod(t_us, self.period_us))
        slot = search_sorted(self.start, key, side="right") - 1
        inside = slot >= 0
        slot = np.maximum(slot, 0)
        return inside & (key <= self.end[slot]) & (key >= self.start[slot])

    def _cumulative(self, key: np.ndarray) -> np.ndarray:
        """Total shadow time of all intervals up to ``key`` (keys of one pixel differ by that pixel's
        shadow time between them)."""
        if self.start.size == 0:
            return np.zeros(key.shape)
        slot = search_sorted(self.start, key, side="right") - 1
        safe = np.maximum(slot, 0)
        partial = np.clip(key - self.start[safe], 0.0, self.end[safe] - self.start[safe])
        return np.where(slot >= 0, self.before[safe] + partial, 0.0)

    def shadowed_us(self, pixel: np.ndarray, t0_us: np.ndarray, t1_us: np.ndarray) -> np.ndarray:
        """(N,) µs that ``pixel`` (N,) spends in shadow between phases ``t0_us`` ≤ ``t1_us`` (N,), at
        most one period apart (any times; reduced modulo the period, wrapping where needed)."""
        arrays = np.broadcast_arrays(np.asarray(pixel, dtype=np.int64), np.asarray(t0_us, dtype=np.float64),
                                     np.asarray(t1_us, dtype=np.float64))
        out = np.zeros(arrays[0].shape)
        busy = self._shadowed_at_all(arrays[0])
        if busy.any():
            out[busy] = self._shadowed_us(*(a[busy] for a in arrays))
        return out

    def _shadowed_us(self, pixel: np.ndarray, t0_us: np.ndarray, t1_us: np.ndarray) -> np.ndarray:
        """``shadowed_us`` by four searches per query."""
        t0 = t0_us
        span = np.clip(np.asarray(t1_us, dtype=np.float64) - t0, 0.0, self.period_us)
        a = np.mod(t0, self.period_us)
        b = a + span
        wraps = b > self.period_us
        low = self._cumulative(self._key(pixel, a))
        high = self._cumulative(self._key(pixel, np.minimum(b, self.period_us)))
        wrapped = self._cumulative(self._key(pixel, np.where(wraps, b - self.period_us, 0.0))) - self._cumulative(self._key(pixel, np.zeros_like(a)))
        return high - low + np.where(wraps, wrapped, 0.0)

    def _rows(self, pixel: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Each pixel's (N,) first and end table rows and its key offset pixel·2·period."""
        base = np.asarray(pixel, dtype=np.int64).astype(np.float64) * (2.0 * self.period_us)
        return search_sorted(self.start, base, side="left"), search_sorted(self.start, base + self.period_us, side="right"), base

    def contains_grid(self, pixel: np.ndarray, t_us: np.ndarray) -> np.ndarray:
        """(T, N) bool: ``contains`` for every pixel (N,) at every phase ``t_us`` (T,)."""
        from pstoolkit.shadows.interval_kernels import contains_on_grid

        out = np.empty((np.size(t_us), np.size(pixel)), dtype=bool)
        contains_on_grid(self.start, self.end, *self._rows(pixel), np.mod(np.asarray(t_us, dtype=np.float64).ravel(), self.period_us), out)
        return out

    def shadowed_grid(self, pixel: np.ndarray, t0_us: np.ndarray, t1_us: np.ndarray) -> np.ndarray:
        """(T, N) µs: ``shadowed_us`` for every pixel (N,) in every window ``t0_us`` ≤ ``t1_us`` (T,)."""
        from pstoolkit.shadows.interval_kernels import overlap_on_grid

        t0 = np.asarray(t0_us, dtype=np.float64).ravel()
        a = np.mod(t0, self.period_us)
        b = a + np.clip(np.asarray(t1_us, dtype=np.float64).ravel() - t0, 0.0, self.period_us)
        out = np.empty((t0.size, np.size(pixel)))
        overlap_on_grid(self.start, self.end, *self._rows(pixel), a, b, self.period_us, out)
        return out

    def coverage(self, n_pixels: int) -> np.ndarray:
        """(n_pixels,) share of the period each pixel spends in shadow."""
        pixel = np.floor(self.start / (2.0 * self.period_us)).astype(np.int64)
        return np.bincount(pixel, weights=self.end - self.start, minlength=n_pixels)[:n_pixels] / self.period_us

    def intervals(self) -> ShadowIntervals:
        """The merged intervals as a ``ShadowIntervals`` (none wraps)."""
        stride = 2.0 * self.period_us
        pixel = np.floor(self.start / stride).astype(np.int64)
        return ShadowIntervals(pixel, self.start - pixel * stride, self.end - pixel * stride)


def _phases(shadows: ShadowIntervals, period: float) -> tuple[np.ndarray, np.ndarray]:
    """Start and end phases in [0, period]; an interval a whole period long (or longer) is [0, period]."""
    t0 = np.asarray(shadows.t0_us, dtype=np.float64)
    t1 = np.asarray(shadows.t1_us, dtype=np.float64)
    whole = t1 - t0 >= period
    return np.where(whole, 0.0, np.mod(t0, period)), np.where(whole, period, np.mod(t1, period))


def grid_times(period_us: float, steps: int) -> np.ndarray:
    """(steps,) phases of a time grid over one period: bin centres (k + ½)·period/steps."""
    return (np.arange(steps) + 0.5) * (float(period_us) / steps)


class RunCollector:
    """The runs of True along the time axis of a (steps, P) bool map of the bins of ``grid_times``,
    fed a block of rows at a time (``feed``), as intervals (``intervals``): a detector sweeping the
    light direction block by block never holds the whole map. Memory: a few bytes per column and the
    runs found."""

    def __init__(self, columns: int) -> None:
        self.previous = np.zeros(columns, dtype=np.uint8)
        self.open_at = np.zeros(columns, dtype=np.int64)
        self.rows = 0
        self._runs: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []

    def feed(self, block: np.ndarray) -> None:
        """The next (n, P) rows, bool."""
        from pstoolkit.shadows.interval_kernels import close_runs, run_closures

        cells = np.ascontiguousarray(block, dtype=bool).view(np.uint8)
        if cells.shape[0] == 0:
            return
        counts = run_closures(cells, self.previous)
        total = int(counts.sum())
        runs = (np.empty(total, dtype=np.int64), np.empty(total, dtype=np.int64), np.empty(total, dtype=np.int64))
        close_runs(cells, self.rows, self.previous, self.open_at, np.cumsum(counts) - counts, *runs)
        self._runs.append(runs)
        self.rows += cells.shape[0]

    def intervals(self, period_us: float, pixels: np.ndarray | None = None) -> ShadowIntervals:
        """Every run of the rows fed so far as [k, j + 1]·period/steps for bins k..j, steps the rows
        fed (runs still open end at the last row), column by column in time order; ``pixels`` (P,)
        names the columns (default 0..P−1)."""
        still = np.flatnonzero(self.previous)
        parts = [*self._runs, (still, self.open_at[still], np.full(still.size, self.rows, dtype=np.int64))]
        column, first, after = (np.concatenate([part[i] for part in parts]) for i in range(3))
        order = np.lexsort((first, column))
        names = np.arange(self.previous.size) if pixels is None else np.asarray(pixels, dtype=np.int64)
        step_us = float(period_us) / max(self.rows, 1)
        return ShadowIntervals(names[column[order]], first[order] * step_us, after[order] * step_us)


def intervals_from_grid(shadowed: np.ndarray, period_us: float, pixels: np.ndarray | None = None) -> ShadowIntervals:
    """Intervals of a (steps, P) bool map of the bins of ``grid_times`` (True: in shadow): each run
    of bins k..j of a pixel becomes [k, j + 1]·period/steps. ``pixels`` (P,) names the columns (default
    0..P−1)."""
    collector = RunCollector(shadowed.shape[1])
    collector.feed(shadowed)
    return collector.intervals(period_us, pixels)


def rasterize(intervals: ShadowIntervals, n_pixels: int, period_us: float, steps: int) -> np.ndarray:
    """(steps, n_pixels) bool: whether each pixel 0..n_pixels−1 is inside one of ``intervals`` at the
    centre of each bin of ``grid_times(period_us, steps)`` (closed intervals, wrapping ones too)."""
    from pstoolkit.shadows.interval_kernels import fill_runs

    step_us = float(period_us) / steps
    t0, t1 = _phases(intervals, float(period_us))
    # bins whose centre (k + ½)·step lies in [t0, t1]; a wrapping interval covers [t0, end) and [0, t1]
    first = np.ceil(t0 / step_us - 0.5).astype(np.int64)
    last = np.floor(t1 / step_us - 0.5).astype(np.int64)
    wraps = t1 < t0
    owners = np.asarray(intervals.pixel, dtype=np.int64)
    # detectors list their intervals pixel by pixel: sorted already, as a rule
    order = np.argsort(owners, kind="stable") if np.any(np.diff(owners) < 0) else np.arange(owners.size)
    owners = owners[order]
    groups = np.r_[0, np.flatnonzero(np.diff(owners)) + 1, owners.size]
    out = np.zeros((steps, n_pixels), dtype=bool)
    fill_runs(out, first[order], last[order], wraps[order], owners, groups)
    return out
