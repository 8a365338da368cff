"""Per-pixel firing state of the reference event engine (``pstoolkit.sim.esim``) under the two
refractory rules of ``pstoolkit.events.rule``: ``Pixels`` ("reset-at-end") and ``PacedPixels``
("rate-limited"), each firing whole sensors on the lines between samples."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

_TINY = np.finfo(np.float64).tiny


@dataclass
class Pixels:
    """Per-pixel state. ``hi``/``lo`` are the levels that fire the next positive/negative event
    (reference + C⁺, reference − C⁻), ±inf while the pixel is blind; ``blind_until_us`` is +inf
    unless a reset to the level at the end of the dead time is pending (``blind`` such pixels)."""

    c_pos: np.ndarray
    c_neg: np.ndarray
    hi: np.ndarray
    lo: np.ndarray
    blind_until_us: np.ndarray
    refractory_us: float
    blind: int = 0

    def set_reference(self, index: np.ndarray, reference: np.ndarray) -> None:
        self.hi[index] = reference + self.c_pos[index]
        self.lo[index] = reference - self.c_neg[index]
        self.blind_until_us[index] = np.inf

    def reset_due(self, ta: float, tb: float, m0: np.ndarray, m1: np.ndarray) -> None:
        """Pixels whose dead time ends within [ta, tb] take the level they see then as reference."""
        due = np.flatnonzero(self.blind_until_us <= tb)
        if due.size:
            frac = (self.blind_until_us[due] - ta) / (tb - ta)
            a = m0[due].astype(np.float64)
            self.set_reference(due, a + frac * (m1[due] - a))
            self.blind -= due.size

    def fire(self, index: np.ndarray, ta: float, tb: float, m0: np.ndarray, m1: np.ndarray,
             ) -> tuple[np.ndarray, ...]:
        """Update the pixels ``index`` whose line from ``m0`` (at ``ta``) to ``m1`` (at ``tb``) reaches a
        firing level, and return what ``_step_all`` expands into events: pixel, sign, first level,
        level gap, event count, start and end of the line. Falling lines are handled as rising ones
        in sign·L."""
        up = m1[index] >= self.hi[index]
        sign = np.where(up, 1.0, -1.0)
        a = sign * m0[index]
        b = sign * m1[index]
        first = np.where(up, self.hi[index], -self.lo[index]).astype(np.float64)
        gap = np.where(up, self.c_pos[index], self.c_neg[index])
        if self.refractory_us > 0:
            slope = np.maximum((b - a) / (tb - ta), _TINY)
            gap = gap + slope * self.refractory_us
        count = np.floor((b - first) / gap).astype(np.int64) + 1
        last = first + (count - 1) * gap
        if self.refractory_us == 0:
            self.set_reference(index, sign * last)
        else:
            blind_until = np.minimum(ta + (last - a) / slope, tb) + self.refractory_us
            now = blind_until <= tb
            self.set_reference(index[now], sign[now] * (last[now] + slope[now] * self.refractory_us))
            later = index[~now]
            self.hi[later], self.lo[later] = np.inf, -np.inf
            self.blind_until_us[later] = blind_until[~now]
            self.blind += later.size
        return index, sign, first, gap, count, a, b

    def advance(self, t_prev: float, m_prev: np.ndarray, times: np.ndarray, block: np.ndarray,
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Events over consecutive samples (t_prev, m_prev), (times[i], block[i]): pixel, time, polarity.

        Only pixels that can fire in the block are stepped: a pixel whose levels stay strictly
        between its firing levels, and which stays blind or sighted throughout, keeps its state.
        Stepping a small subset saves the per-step passes over the whole sensor where few pixels
        are active (around shadow edges, when the sampling is fine)."""
        candidates = np.flatnonzero(self._may_fire(m_prev, times, block))
        if 2 * candidates.size > block.shape[1]:
            return self._step_all(t_prev, m_prev, times, block)
        if candidates.size == 0:
            return np.empty(0, np.int64), np.empty(0), np.empty(0, np.int8)
        blind = int(np.count_nonzero(np.isfinite(self.blind_until_us[candidates])))
        sub = type(self)(self.c_pos[candidates], self.c_neg[candidates], self.hi[candidates], self.lo[candidates],
                         self.blind_until_us[candidates], self.refractory_us, blind)
        pix, t, pol = sub._step_all(t_prev, m_prev[candidates], times, block[:, candidates])
        self.hi[candidates], self.lo[candidates], self.blind_until_us[candidates] = sub.hi, sub.lo, sub.blind_until_us
        self.blind += sub.blind - blind
        return candidates[pix], t, pol

    def _may_fire(self, m_prev: np.ndarray, times: np.ndarray, block: np.ndarray) -> np.ndarray:
        """(pixels,) bool: whether a pixel can fire in the block (it reaches a firing level, or a
        reset falls due in it)."""
        return (block.max(axis=0) >= self.hi) | (block.min(axis=0) <= self.lo) | (self.blind_until_us <= times[-1])

    def _firing(self, m0: np.ndarray, m1: np.ndarray) -> np.ndarray:
        """The pixels that fire on the line from ``m0`` to ``m1`` (resets due on it done)."""
        return np.flatnonzero((m1 >= self.hi) | (m1 <= self.lo))

    def _step_all(self, t_prev: float, m_prev: np.ndarray, times: np.ndarray, block: np.ndarray,
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Steps run in order (each depends on the state the previous left); the events are
        expanded once per block."""
        t_all = np.concatenate(([t_prev], times))
        bounds = t_all.tolist()
        fired, steps = [], []
        m0 = m_prev
        for s, m1 in enumerate(block):
            if self.blind:
                self.reset_due(bounds[s], bounds[s + 1], m0, m1)
            index = self._firing(m0, m1)
            if index.size:
                fired.append(self.fire(index, bounds[s], bounds[s + 1], m0, m1))
                steps.append(s)
            m0 = m1
        if not fired:
            return np.empty(0, np.int64), np.empty(0), np.empty(0, np.int8)
        return self._expand(fired, steps, t_all)

    @staticmethod
    def _expand(fired: list[tuple[np.ndarray, ...]], steps: list[int], t_all: np.ndarray,
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The events of a block from what ``fire`` returned at ``steps`` (sample times ``t_all``):
        each firing level placed on its line."""
        sizes = [len(f[0]) for f in fired]
        index, sign, first, gap, count, a, b = (np.concatenate(c) for c in zip(*fired))
        step = np.repeat(np.array(steps), sizes)
        owner = np.repeat(np.arange(len(count)), count)
        k = np.arange(len(owner)) - (np.cumsum(count) - count)[owner]
        level = first[owner] + k * gap[owner]
        a, step = a[owner], step[owner]
        frac = np.clip((level - a) / np.maximum(b[owner] - a, _TINY), 0.0, 1.0)
        t = t_all[step] + frac * (t_all[step + 1] - t_all[step])
        return index[owner], t, sign[owner].astype(np.int8)


class PacedPixels(Pixels):
    """Per-pixel state of the "rate-limited" rule (R > 0): ``hi``/``lo`` are always the reference
    ± C (float64: the reference moves by whole thresholds), ``blind_until_us`` the end of the blind
    time (−inf before the first event); there is no reset to apply."""

    def reset_due(self, ta: float, tb: float, m0: np.ndarray, m1: np.ndarray) -> None:
        """Nothing: the reference does not move at the end of a blind time."""

    def _may_fire(self, m_prev: np.ndarray, times: np.ndarray, block: np.ndarray) -> np.ndarray:
        # a level beyond a firing level before the block (a lag still to fire) counts too
        top = np.maximum(block.max(axis=0), m_prev)
        bottom = np.minimum(block.min(axis=0), m_prev)
        return (top >= self.hi) | (bottom <= self.lo)

    def _firing(self, m0: np.ndarray, m1: np.ndarray) -> np.ndarray:
        return np.flatnonzero((np.maximum(m0, m1) >= self.hi) | (np.minimum(m0, m1) <= self.lo))

    def fire(self, index: np.ndarray, ta: float, tb: float, m0: np.ndarray, m1: np.ndarray,
             ) -> tuple[np.ndarray, ...]:
        """Update the pixels ``index`` over the line from ``m0`` (at ``ta``) to ``m1`` (at ``tb``)
        and return their events as two runs each (``_expand``): first a lag left over from before,
        firing against the line's sense every R from the end of the blind time while the level stays
        beyond the moving threshold; then the line's own run, whose k-th event is at
        max(t₁ + (k − 1)·R, t_c + (k − 1)·C/|s|), t_c the crossing of its first threshold (before
        ``ta`` for a lag in the line's sense) and t₁ the first time the pixel may fire at or after
        t_c. Returns pixel, and per run count, start t₁, crossing t_c, spacing C/|s| and sign."""
        r = self.refractory_us
        a, b = m0[index].astype(np.float64), m1[index].astype(np.float64)
        hi, lo, blind = self.hi[index], self.lo[index], self.blind_until_us[index]
        c_pos, c_neg = self.c_pos[index], self.c_neg[index]
        slope = (b - a) / (tb - ta)
        speed = np.abs(slope)
        # the lag run: beyond a threshold when the pixel may first fire, against the line (or flat)
        t1 = np.maximum(blind, ta)
        level = a + slope * (t1 - ta)
        up, down = (t1 <= tb) & (level >= hi), (t1 <= tb) & (level <= lo)
        sign1 = np.where(up, 1.0, -1.0)
        lag = (up | down) & (sign1 * slope <= 0)
        c1 = np.where(up, c_pos, c_neg)
        beyond = sign1 * level - np.where(up, hi, -lo)
        n1 = np.minimum(np.floor(beyond / (c1 + speed * r)), np.floor((tb - t1) / r)) + 1
        n1 = np.where(lag, n1, 0.0)
        hi, lo = hi + sign1 * n1 * c1, lo + sign1 * n1 * c1
        blind = np.where(n1 > 0, t1 + n1 * r, blind)
        # the line's run
        rising = slope > 0
        sign2 = np.where(rising, 1.0, -1.0)
        c2 = np.where(rising, c_pos, c_neg)
        first = np.where(rising, hi, -lo)
        inverse = 1.0 / np.maximum(speed, _TINY)
        with np.errstate(over="ignore", invalid="ignore"):
            crossing = ta + (first - sign2 * a) * inverse
            t2 = np.maximum(np.maximum(blind, ta), crossing)
            n2 = np.minimum(np.floor((sign2 * b - first) / c2), np.floor((tb - t2) / r)) + 1
        n2 = np.where((slope != 0) & (t2 <= tb) & (sign2 * b >= first), n2, 0.0)
        spacing = c2 * inverse
        hi, lo = hi + sign2 * n2 * c2, lo + sign2 * n2 * c2
        with np.errstate(over="ignore", invalid="ignore"):
            last = np.maximum(t2 + (n2 - 1) * r, crossing + (n2 - 1) * spacing)
        self.hi[index], self.lo[index] = hi, lo
        self.blind_until_us[index] = np.where(n2 > 0, last + r, blind)
        counts = np.stack([n1, n2]).astype(np.int64)
        return index, counts, np.stack([t1, t2]), np.stack([t1, crossing]), np.stack([np.zeros_like(t1), spacing]), np.stack([sign1, sign2])

    def _expand(self, fired: list[tuple[np.ndarray, ...]], steps: list[int], t_all: np.ndarray,  # type: ignore[override]
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The events of a block from ``fire``'s runs, step by step and within a step the lag run
        first: the k-th (from 0) of a run at max(start + k·R, crossing + k·spacing)."""
        pixel = np.concatenate([np.tile(f[0], 2) for f in fired])
        count, start, crossing, spacing, sign = (np.concatenate([a.reshape(-1) for a in c]) for c in list(zip(*fired))[1:])
        owner = np.repeat(np.arange(count.size), count)
        k = np.arange(owner.size) - np.repeat(np.cumsum(count) - count, count)
        t = np.maximum(start[owner] + k * self.refractory_us, crossing[owner] + k * spacing[owner])
        return pixel[owner], t, sign[owner].astype(np.int8)
