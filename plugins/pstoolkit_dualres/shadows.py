"""Cast-shadow intervals from the event interval profile: Algorithm 1 of the DualResPS supplement.

A spike f > θ is a shadow exit, f < −θ an entry. Pass ρ = +1 takes every exit spike as an anchor,
searches backwards (within the max duration D, cyclically over the period) for the farthest entry
whose |f| exceeds a threshold θ' that starts at θ and decays by γ (the last step clamped to θ_min)
while none is found
(an entry softened by attached shadow is a weak spike), then forwards from that entry for the
farthest strong exit (|f| > θ) within D: the shadow is [entry, exit]. Pass ρ = −1 does the mirror
image from entry anchors not inside a shadow found already. Every anchor of a pass is searched at
once with array operations over (anchor, candidate offset) blocks; only the threshold decay loops.

Intervals are phases in [0, period_us); t1 < t0 means the shadow wraps past the period's end.
``ShadowTable`` merges overlapping intervals and answers "is pixel x in shadow at phase t" for many
queries at once by one ``searchsorted``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pstoolkit_dualres.profile import Profile

# Anchors searched per block, so one block's (anchor, offset) arrays hold about this many values.
BLOCK_VALUES = 1 << 22


@dataclass
class ShadowIntervals:
    """Shadow intervals: flat event ``pixel`` (S,), phases ``t0_us``, ``t1_us`` (S,) in µs (float64)."""

    pixel: np.ndarray
    t0_us: np.ndarray
    t1_us: np.ndarray

    def __len__(self) -> int:
        return len(self.pixel)


def _farthest(profile: Profile, anchors: np.ndarray, direction: int, sign: int, threshold: float, max_us: float) -> np.ndarray:
    """For each anchor, the sample of the same pixel farthest from it in ``direction`` (+1 later,
    −1 earlier, cyclic gap in (0, max_us)) with sign·f > threshold; −1 where there is none."""
    out = np.full(len(anchors), -1, dtype=np.int64)
    if len(anchors) == 0:
        return out
    period = profile.period_us
    widest = int(profile.count[anchors].max())
    offsets = np.arange(1, widest, dtype=np.int64)
    if offsets.size == 0:
        return out
    step = max(1, BLOCK_VALUES // offsets.size)
    for start in range(0, len(anchors), step):
        a = anchors[start : start + step]
        local = (a - profile.first[a])[:, None]
        count = profile.count[a][:, None]
        candidate = profile.first[a][:, None] + np.mod(local + direction * offsets[None, :], count)
        gap = np.mod(direction * (profile.t_us[candidate] - profile.t_us[a][:, None]), period)
        ok = (offsets[None, :] < count) & (gap > 0) & (gap < max_us) & (sign * profile.f[candidate] > threshold)
        # gaps grow with the offset within a pixel, so the farthest valid one is the last valid one
        last = ok.shape[1] - 1 - np.argmax(ok[:, ::-1], axis=1)
        found = ok.any(axis=1)
        out[start : start + step] = np.where(found, candidate[np.arange(len(a)), last], -1)
    return out


def find_shadows(
    profile: Profile,
    *,
    theta: float,
    theta_min: float,
    gamma: float,
    max_duration_us: float,
) -> ShadowIntervals:
    """Algorithm 1 (FINDSHADOWBOUNDARIES) at every super pixel of ``profile``; thresholds in log units
    per second, ``gamma`` in (0, 1) the decay factor, ``max_duration_us`` the longest shadow D."""
    pixels, starts, ends = [], [], []
    covered = np.zeros(len(profile), dtype=bool)
    for rho in (1, -1):
        anchors = np.flatnonzero((rho * profile.f > theta) & ~covered)
        opposite = np.full(len(anchors), -1, dtype=np.int64)
        level = theta
        while True:
            todo = np.flatnonzero(opposite < 0)
            if todo.size == 0:
                break
            # ρ = +1: entries (f < −θ') before the exit anchor; ρ = −1: exits (f > θ') after the entry
            opposite[todo] = _farthest(profile, anchors[todo], -rho, -rho, level, max_duration_us)
            if level <= theta_min:
                break
            level = max(level * gamma, theta_min)
        keep = opposite >= 0
        anchors, opposite = anchors[keep], opposite[keep]
        confirm = _farthest(profile, opposite, rho, rho, theta, max_duration_us)
        keep = confirm >= 0
        opposite, confirm = opposite[keep], confirm[keep]
        lo, hi = (opposite, confirm) if rho > 0 else (confirm, opposite)
        pixels.append(profile.pixel[lo])
        starts.append(profile.t_us[lo])
        ends.append(profile.t_us[hi])
        covered |= _covered(profile, lo, hi)
    # anchors of one shadow (every event of its exit burst) find the same interval: keep one
    found = np.unique(np.stack([np.concatenate(pixels), np.concatenate(starts), np.concatenate(ends)], axis=1), axis=0)
    return ShadowIntervals(found[:, 0].astype(np.int64), found[:, 1], found[:, 2])


def _covered(profile: Profile, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Samples lying within one of the intervals [lo, hi] (sample indices, cyclic within a pixel)."""
    table = ShadowTable.build(ShadowIntervals(profile.pixel[lo], profile.t_us[lo], profile.t_us[hi]), profile.period_us)
    return table.contains(profile.pixel, profile.t_us)


@dataclass
class ShadowTable:
    """Merged, non-wrapping shadow intervals keyed by pixel·2·period + phase, for vectorised lookups:
    ``start``/``end`` (S,) float64 keys, sorted, disjoint; closed intervals. The stride of two
    periods keeps one pixel's interval ending at the period apart from the next pixel's at 0."""

    start: np.ndarray
    end: np.ndarray
    period_us: float

    @classmethod
    def build(cls, shadows: ShadowIntervals, period_us: float) -> ShadowTable:
        period = float(period_us)
        t0 = np.mod(shadows.t0_us, period)
        t1 = np.mod(shadows.t1_us, period)
        wraps = t1 < t0
        base = shadows.pixel.astype(np.float64) * (2.0 * period)
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
        return cls(start=start, end=end, period_us=period)

    def __len__(self) -> int:
        return len(self.start)

    def contains(self, pixel: np.ndarray, t_us: np.ndarray) -> np.ndarray:
        """(N,) bool: whether event pixel ``pixel`` (N,) is in shadow at time ``t_us`` (N,) (any time;
        reduced modulo the period, so phase 0 is the phase origin the intervals were found in)."""
        pixel = np.asarray(pixel, dtype=np.int64)
        key = pixel.astype(np.float64) * (2.0 * self.period_us) + np.mod(np.asarray(t_us, dtype=np.float64), self.period_us)
        if self.start.size == 0:
            return np.zeros(key.shape, dtype=bool)
        slot = np.searchsorted(self.start, key, side="right") - 1
        inside = slot >= 0
        slot = np.maximum(slot, 0)
        return inside & (key <= self.end[slot]) & (key >= self.start[slot])

    def coverage(self, n_pixels: int) -> np.ndarray:
        """(n_pixels,) share of the period each event pixel spends in shadow."""
        pixel = np.floor(self.start / (2.0 * self.period_us)).astype(np.int64)
        return np.bincount(pixel, weights=self.end - self.start, minlength=n_pixels) / self.period_us


def find_silences(
    profile: Profile, *, ratio: float, refractory_us: float, max_duration_us: float
) -> ShadowIntervals:
    """Shadows of a sensor whose refractory period hides the bursts at shadow edges.

    With the reset-at-end refractory rule of ``pstoolkit.eventmodel`` an edge fires one event and
    the pixel then resets to the new level, so a shadow shows as a dimming event, a silence, and a
    brightening event, with no spike in f. A silence from t_{k−1} to t_k is taken as a shadow when
    p_{k−1} = −1, p_k = +1, it is longer than 2R and shorter than ``max_duration_us``, and longer
    than ``ratio`` times both neighbouring intervals (a smooth shading minimum slows the events
    gradually instead). The shadow is [t_{k−1} + R/2, t_k]: an entry inside the refractory period
    after t_{k−1} fires nothing, so it lies in [t_{k−1}, t_{k−1} + R]; the exit fires at once.
    On the simulated blobs scene (64 px, R = 2 ms) a 1 ms later start raises the precision from
    0.74 to 0.82 at the same recall (0.45)."""
    period = profile.period_us
    k = np.arange(len(profile))
    prev, prev2, nxt = profile.neighbour(k, -1), profile.neighbour(k, -2), profile.neighbour(k, 1)
    gap = np.mod(profile.t_us - profile.t_us[prev], period)
    gap_before = np.mod(profile.t_us[prev] - profile.t_us[prev2], period)
    gap_after = np.mod(profile.t_us[nxt] - profile.t_us, period)
    hit = (
        (profile.count >= 3)
        & (profile.p > 0)
        & (profile.p[prev] < 0)
        & (gap > 2.0 * refractory_us)
        & (gap < max_duration_us)
        & (gap > ratio * np.maximum(gap_before, gap_after))
    )
    start = np.mod(profile.t_us[prev[hit]] + 0.5 * refractory_us, period)
    return ShadowIntervals(profile.pixel[hit], start, profile.t_us[hit])
