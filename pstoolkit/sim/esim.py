"""ESIM-style event simulation (Rebecq et al., ESIM, CoRL 2018) from a render callback.

``render(t_us) -> (T, height, width)`` gives linear grey irradiance (≥ 0) at the event resolution;
each pixel sees ``L = ln(I + ε)`` and fires by the rule of ``pstoolkit.events.rule``:

- **Sampling.** Render times are chosen adaptively: a block of up to ``chunk_samples`` times at the
  current step is rendered at once; every interval whose largest per-pixel ``|ΔL|`` exceeds
  ``max_dlog`` (default half the smaller contrast) is split into ``⌈|ΔL| / max_dlog⌉`` equal parts and
  the new times rendered, until no interval exceeds it or is shorter than ``min_dt_us``. The step of
  the next block follows the mean step of this one, doubled at most when the block changed little.
  Memory is bounded: ``render`` never receives more than ``chunk_samples`` times, and a few blocks
  of at most ``chunk_samples`` float32 log frames are held — never a (T × H × W) array of the whole
  span. As in ESIM, a change that starts and ends between two samples is not seen. The number of
  samples is set by the fastest pixel: a pixel leaving attached shadow (I from 0, so ln(I + ε)
  jumps by ≈ 7) forces steps near ``min_dt_us``, and the cost is about samples × pixels.
- **Per-pixel refinement** (optional ``render_pixels(t_us, pixel)``, single pixels at single times):
  a split interval's new times are rendered only for the pixels whose own ``|ΔL|`` over it exceeds
  ``max_dlog``; every other pixel takes the value on its line, which is what the rule above assumes
  of it anyway, so each pixel is sampled as finely as it needs and no finer. The whole-frame renders
  then follow the share of pixels needing refinement (see ``_adaptive_blocks``), or fixed times
  (``sample_times_us``), and a terminator sweeping the sensor costs a few pixels per fine step
  instead of whole frames (the simulator's 256² sphere, one turn: 1383 whole-frame renders before;
  now only the frames' 510 midpoint samples, shared with them, plus ~0.2 M single event pixels).
- **Crossings.** ``L`` (held in float32, ≈ 1e-6 absolute) is linear between samples; every crossing
  inside a step is emitted at its own exact time on that line (float64), then rounded half up to
  int64 µs. Positive events step the reference by ``C⁺``, negative by ``C⁻``; per-pixel thresholds
  are drawn once from ``N(C, σ)`` and clamped to ≥ 0.01.
- **Refractory** (``refractory_rule``, one of ``pstoolkit.events.rule.REFRACTORY_RULES``): after an event at
  ``t`` the pixel cannot fire before ``t + R``. "reset-at-end" (the default): what happens in the
  dead time is not emitted, and at ``t + R`` the reference is reset to ``L(t + R)``; on a line of
  slope ``s`` a pixel fires every ``R + C / |s|``. "rate-limited": the reference moves by one
  threshold per event and a level still beyond a threshold at ``t + R`` fires then, so a line
  steeper than ``C / R`` fires every ``R`` while the reference lags behind (``_PacedPixels``: on
  each line between samples the events are the closed form of ``pstoolkit.sim.ring_engine``'s
  ``_fire_lanes_paced``). With ``R = 0`` the two are the same rule, ESIM's, and run as
  "reset-at-end".
- **Leak** (v2e-style, optional): each pixel's reference drifts down by ``leak_hz · C⁺`` per second,
  so a static pixel fires positive events at ``leak_hz``; the start reference is lowered by a uniform
  random fraction of ``C⁺`` (seeded) so that static pixels do not fire in lockstep.
- **Shot noise** (optional): a Poisson process of rate ``shot_noise_hz`` per pixel with random
  polarity, added on top; shot events obey no refractory and leave the reference untouched.

Output: ``EventArray`` chunks in time order — each sorted by ``t`` and then by pixel (y·width + x),
each starting no earlier than the previous one ended; times lie in ``[t0_us, t1_us]``. The same
arguments and seed give the same events.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import partial

import numpy as np

from psfmt import EventArray
from pstoolkit.errors import UserError
from pstoolkit.events.rule import LOG_EPS, REFRACTORY_RULE, REFRACTORY_RULES, check_rule, log_irradiance

MIN_CONTRAST = 0.01
Render = Callable[[np.ndarray], np.ndarray]
RenderPixels = Callable[[np.ndarray, np.ndarray], np.ndarray]
# Shares of the sensor's pixels needing refinement in one interval above / below which the step of
# full renders is halved / doubled when pixels can be rendered alone (``render_pixels``): full
# renders are cheaper per pixel, so they should carry all but a few per cent of the pixels.
REFINE_SHARE_HIGH = 0.02
REFINE_SHARE_LOW = 0.002


def check_options(
    t0_us: float, t1_us: float, width: int, height: int, contrasts: dict[str, float], sigma: float,
    refractory_us: float, eps: float, max_dlog: float, initial_dt_us: float, chunk_samples: int,
    min_dt_us: float, rates: dict[str, float], caller: str = "simulate_events",
) -> None:
    """UserError naming the first argument of ``simulate_events`` (or of an engine with the same
    options) that is out of range."""
    if not t1_us > t0_us:
        raise UserError(f"{caller}: t1_us ({t1_us}) must be after t0_us ({t0_us})")
    if width < 1 or height < 1 or width > 65536 or height > 65536:
        raise UserError(f"{caller}: sensor size {width}x{height} must be 1 to 65536 pixels per side")
    positive = {**contrasts, "eps": eps, "max_dlog": max_dlog, "initial_dt_us": initial_dt_us,
                "min_dt_us": min_dt_us}
    nonnegative = {"sigma": sigma, "refractory_us": refractory_us, **rates}
    for name, value in positive.items():
        if not value > 0 or not math.isfinite(value):
            raise UserError(f"{caller}: {name} must be a positive number, got {value}")
    for name, value in nonnegative.items():
        if not value >= 0 or not math.isfinite(value):
            raise UserError(f"{caller}: {name} must be zero or positive, got {value}")
    if chunk_samples < 2:
        raise UserError(f"{caller}: chunk_samples must be at least 2, got {chunk_samples}")


def _check_sample_times(sample_times_us: np.ndarray, t0_us: float, t1_us: float) -> np.ndarray:
    times = np.asarray(sample_times_us, dtype=np.float64).reshape(-1)
    if times.size and not (times[0] > t0_us and times[-1] < t1_us and np.all(np.diff(times) > 0)):
        raise UserError("simulate_events: sample_times_us must increase strictly inside (t0_us, t1_us)")
    return np.append(times, t1_us)


def event_rngs(seed: int) -> tuple[np.random.Generator, np.random.Generator, np.random.Generator]:
    """The independent random streams of an event simulation with ``seed``: thresholds, leak, shot noise."""
    thresholds, leak, shot = (np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(3))
    return thresholds, leak, shot


def draw_thresholds(rng: np.random.Generator, contrast_pos: float, contrast_neg: float, sigma: float, n_pixels: int,
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel contrast thresholds C⁺ and C⁻, each ``N(contrast, sigma)`` clamped to ≥ ``MIN_CONTRAST``."""
    if sigma == 0:
        return (np.full(n_pixels, max(contrast_pos, MIN_CONTRAST)), np.full(n_pixels, max(contrast_neg, MIN_CONTRAST)))
    return tuple(np.maximum(rng.normal(c, sigma, n_pixels), MIN_CONTRAST) for c in (contrast_pos, contrast_neg))  # type: ignore[return-value]


def _log_frames(render: Render, t_us: np.ndarray, shape: tuple[int, int], eps: float) -> np.ndarray:
    """``ln(I + ε)`` of the rendered frames, flattened to (T, H·W)."""
    irradiance = np.asarray(render(t_us))
    if irradiance.shape != (len(t_us), *shape):
        raise UserError(f"simulate_events: render returned shape {irradiance.shape}, expected {(len(t_us), *shape)}")
    if not (irradiance.min() >= 0 and np.isfinite(irradiance.max())):
        raise UserError("simulate_events: render returned negative or non-finite irradiance")
    return log_irradiance(irradiance, eps, np.float32).reshape(len(t_us), -1)


def _log_pixels(render_pixels: RenderPixels, t_us: np.ndarray, pixel: np.ndarray, eps: float) -> np.ndarray:
    """``ln(I + ε)`` of single pixels at single times, float32."""
    irradiance = np.asarray(render_pixels(t_us, pixel))
    if irradiance.shape != (len(t_us),):
        raise UserError(f"simulate_events: render_pixels returned shape {irradiance.shape}, expected {(len(t_us),)}")
    if not (irradiance.size == 0 or (irradiance.min() >= 0 and np.isfinite(irradiance.max()))):
        raise UserError("simulate_events: render_pixels returned negative or non-finite irradiance")
    return log_irradiance(irradiance, eps, np.float32)


def _largest_change(l_prev: np.ndarray, block: np.ndarray) -> np.ndarray:
    """Largest per-pixel |ΔL| of each interval: from ``l_prev`` to ``block[0]``, then along ``block``."""
    out = np.empty(len(block))
    out[0] = np.abs(block[0] - l_prev).max()
    if len(block) > 1:
        diff = np.diff(block, axis=0)
        out[1:] = np.maximum(diff.max(axis=1), -diff.min(axis=1))
    return out


def _rows_change(l_prev: np.ndarray, block: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Largest per-pixel |ΔL| of the intervals ending at ``rows`` of ``block``."""
    before = block[np.maximum(rows - 1, 0)]
    before[rows == 0] = l_prev
    return np.abs(block[rows] - before).max(axis=1)


def _refine(
    log_render: Callable[[np.ndarray], np.ndarray], log_render_pixels: RenderPixels | None, t_prev: float,
    l_prev: np.ndarray, times: np.ndarray, block: np.ndarray, max_dlog: float, min_dt_us: float, cap: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split intervals whose |ΔL| exceeds ``max_dlog`` until none does, keeping at most ``cap`` samples
    (a prefix of the block: later samples are dropped rather than held). Returns times, frames and
    each interval's largest |ΔL|. With ``log_render_pixels`` only the pixels whose own |ΔL| over a
    split interval exceeds ``max_dlog`` are rendered at the new times; the others take the value on
    their line, which is what they would be assumed to do anyway."""
    change = _largest_change(l_prev, block)
    while True:
        starts = np.concatenate(([t_prev], times[:-1]))
        lengths = times - starts
        pieces = np.where(
            change > max_dlog,
            np.minimum(np.ceil(change / max_dlog), np.floor(lengths / min_dt_us)),
            1,
        ).astype(np.int64)
        pieces = np.maximum(pieces, 1)
        if np.all(pieces == 1):
            return times, block, change
        keep = max(1, int(np.searchsorted(np.cumsum(pieces), cap, side="right")))
        pieces = pieces[:keep]
        pieces[0] = min(pieces[0], cap)
        if np.all(pieces == 1):
            # the cap fell just before the first interval to split: the prefix is final as it is
            return times[:keep], block[:keep], change[:keep]
        ends = np.cumsum(pieces) - 1
        new_count = pieces - 1
        owner = np.repeat(np.arange(keep), new_count)
        rank = np.arange(len(owner)) - np.repeat(np.cumsum(new_count) - new_count, new_count) + 1
        new_slots = ends[owner] - pieces[owner] + rank
        merged_times = np.empty(ends[-1] + 1)
        merged_times[ends] = times[:keep]
        merged_times[new_slots] = starts[owner] + lengths[owner] * rank / pieces[owner]
        merged = np.empty((ends[-1] + 1, block.shape[1]), dtype=block.dtype)
        merged[ends] = block[:keep]
        if log_render_pixels is None:
            merged[new_slots] = log_render(merged_times[new_slots])
        else:
            _fill_split(log_render_pixels, merged, merged_times, l_prev, ends, owner, rank, pieces, new_slots, max_dlog)
        merged_change = np.empty(ends[-1] + 1)
        merged_change[ends] = change[:keep]
        redo = np.concatenate((new_slots, ends[pieces > 1]))
        merged_change[redo] = _rows_change(l_prev, merged, redo)
        times, block, change = merged_times, merged, merged_change


def _fill_split(
    log_render_pixels: RenderPixels, merged: np.ndarray, merged_times: np.ndarray, l_prev: np.ndarray,
    ends: np.ndarray, owner: np.ndarray, rank: np.ndarray, pieces: np.ndarray, new_slots: np.ndarray,
    max_dlog: float,
) -> None:
    """Fill the new rows ``new_slots`` of ``merged``: every pixel on the line between its owner
    interval's end samples, then the pixels whose change over that interval exceeds ``max_dlog``
    rendered at the new times."""
    end_rows = ends[owner]
    start_rows = end_rows - pieces[owner]
    end = merged[end_rows]
    start = merged[np.maximum(start_rows, 0)]
    start[start_rows < 0] = l_prev
    change = end - start
    frac = (rank / pieces[owner]).astype(merged.dtype)[:, None]
    filled = start + frac * change
    row, pixel = np.nonzero(np.abs(change) > max_dlog)
    if row.size:
        filled[row, pixel] = log_render_pixels(merged_times[new_slots][row], pixel)
    merged[new_slots] = filled


def _share_over(l_prev: np.ndarray, block: np.ndarray, max_dlog: float) -> float:
    """Largest share of pixels whose |ΔL| exceeds ``max_dlog`` over one interval of the block."""
    before = np.concatenate((l_prev[None], block[:-1]))
    return float((np.abs(block - before) > max_dlog).mean(axis=1).max())


def _adaptive_blocks(
    log_render: Callable[[np.ndarray], np.ndarray], log_render_pixels: RenderPixels | None, t0_us: float,
    t1_us: float, l_start: np.ndarray, max_dlog: float, initial_dt_us: float, min_dt_us: float, cap: int,
    sample_times_us: np.ndarray | None = None,
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Blocks of (sample times (n,), log frames (n, H·W)) covering (t0_us, t1_us], in order; the full
    renders are at ``sample_times_us`` (sorted, ending at ``t1_us``) when given, else stepped adaptively.

    Without ``log_render_pixels`` the step of the next block follows the mean step of this one
    (refinement included). With it, refinement is per pixel and cheap, so the step of the full
    renders follows the share of pixels that needed refining instead: halved above
    ``REFINE_SHARE_HIGH``, doubled below ``REFINE_SHARE_LOW``. A block then renders at most a
    quarter of ``cap`` full frames, leaving room for the refined samples."""
    t_prev, l_prev, dt = float(t0_us), l_start, float(initial_dt_us)
    base_cap = cap if log_render_pixels is None else max(2, cap // 4)
    while t_prev < t1_us:
        if sample_times_us is not None:
            first = int(np.searchsorted(sample_times_us, t_prev, side="right"))
            times = sample_times_us[first : first + base_cap]
        else:
            n = int(min(base_cap, math.ceil((t1_us - t_prev) / dt)))
            times = t_prev + dt * np.arange(1, n + 1)
            times[-1] = min(times[-1], t1_us)
        block = log_render(times)
        adaptive = log_render_pixels is not None and sample_times_us is None
        share = _share_over(l_prev, block, max_dlog) if adaptive else 0.0
        times, block, change = _refine(log_render, log_render_pixels, t_prev, l_prev, times, block, max_dlog,
                                       min_dt_us, cap)
        if log_render_pixels is None:
            mean_step = (times[-1] - t_prev) / len(times)
            dt = mean_step * float(np.clip(0.8 * max_dlog / max(change.max(), 1e-12), 1.0, 2.0))
        elif share > REFINE_SHARE_HIGH:
            dt = max(0.5 * dt, min_dt_us)
        elif share < REFINE_SHARE_LOW:
            dt = 2.0 * dt
        t_prev, l_prev = float(times[-1]), block[-1].copy()
        yield times, block


_TINY = np.finfo(np.float64).tiny


@dataclass
class _Pixels:
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


class _PacedPixels(_Pixels):
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


def _shot_noise(rng: np.random.Generator, rate_hz: float, n_pixels: int, ta: float, tb: float,
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    count = rng.poisson(rate_hz * n_pixels * (tb - ta) * 1e-6)
    return (rng.integers(0, n_pixels, count), rng.uniform(ta, tb, count),
            (2 * rng.integers(0, 2, count) - 1).astype(np.int8))


def _sorted_chunk(pix: np.ndarray, t: np.ndarray, pol: np.ndarray, width: int, n_pixels: int) -> EventArray:
    """Round times half up to µs and sort by (t, pixel); the sort is stable, so a pixel's events that
    round to the same µs keep their order."""
    t_us = np.floor(t + 0.5).astype(np.int64)
    key = (t_us - t_us.min()) * n_pixels + pix
    order = np.argsort(key, kind="stable")
    pix, t_us = pix[order], t_us[order]
    return EventArray(x=pix % width, y=pix // width, t=t_us, p=pol[order])


def simulate_events(
    render: Render,
    t0_us: float,
    t1_us: float,
    *,
    width: int,
    height: int,
    contrast_pos: float = 0.15,
    contrast_neg: float = 0.15,
    sigma: float = 0.0,
    refractory_us: float = 0.0,
    eps: float = LOG_EPS,
    seed: int = 0,
    max_dlog: float | None = None,
    initial_dt_us: float = 100.0,
    chunk_samples: int = 64,
    min_dt_us: float = 1.0,
    shot_noise_hz: float = 0.0,
    leak_hz: float = 0.0,
    render_pixels: RenderPixels | None = None,
    sample_times_us: np.ndarray | None = None,
    refractory_rule: str = REFRACTORY_RULE,
) -> Iterator[EventArray]:
    """Events of a ``width``×``height`` sensor watching ``render`` from ``t0_us`` to ``t1_us`` (see the
    module docstring for the model). Yields non-empty ``EventArray`` chunks in time order.

    ``eps`` defaults to ``pstoolkit.events.rule.LOG_EPS`` (1e-3, for irradiance normalised to ≈ 1 when bright);
    ``sigma`` is the per-pixel threshold spread, ``refractory_us`` the dead time and
    ``refractory_rule`` what happens in it (``pstoolkit.events.rule.REFRACTORY_RULES``), ``max_dlog`` the
    largest log change allowed between samples (default ``0.5·min(C⁺, C⁻)``), ``initial_dt_us`` the
    first sampling step, ``chunk_samples`` the most times rendered or held at once, ``min_dt_us`` the
    shortest interval that is still split (a jump in irradiance is resolved to this), ``leak_hz`` and
    ``shot_noise_hz`` the noise rates per pixel. ``render_pixels(t_us (M,), pixel (M,)) -> (M,)``,
    optional, gives the irradiance of single pixels (``pixel`` = y·width + x) at single times: with
    it, refinement renders only the pixels that need it (see the module docstring).
    ``sample_times_us``, optional, fixes the times of the whole-frame renders (increasing, inside
    (t0_us, t1_us); t1_us is added) instead of the adaptive steps, so a caller can share them with
    other work (the simulator integrates its frames on them); refinement still applies.
    """
    if max_dlog is None:
        max_dlog = 0.5 * min(contrast_pos, contrast_neg)
    check_options(t0_us, t1_us, width, height, {"contrast_pos": contrast_pos, "contrast_neg": contrast_neg},
                   sigma, refractory_us, eps, max_dlog, initial_dt_us, chunk_samples, min_dt_us,
                   {"shot_noise_hz": shot_noise_hz, "leak_hz": leak_hz})
    check_rule(refractory_rule, "simulate_events")
    if sample_times_us is not None:
        sample_times_us = _check_sample_times(sample_times_us, float(t0_us), float(t1_us))
    n_pixels = width * height
    rng_thresholds, rng_leak, rng_shot = event_rngs(seed)
    c_pos, c_neg = draw_thresholds(rng_thresholds, contrast_pos, contrast_neg, sigma, n_pixels)

    def log_render(t_us: np.ndarray) -> np.ndarray:
        return _log_frames(render, t_us, (height, width), eps)

    l_start = log_render(np.array([float(t0_us)]))[0]
    reference = l_start.astype(np.float64)
    # Leak is a downward drift of the reference; it is applied as the equal upward drift
    # leak_per_us·(t − t0) of the signal, which keeps the signal piecewise linear.
    leak_per_us = leak_hz * 1e-6 * c_pos
    if leak_hz > 0:
        reference -= rng_leak.uniform(0.0, 1.0, n_pixels) * c_pos
    if refractory_rule == REFRACTORY_RULES[1] and refractory_us > 0:
        pixels: _Pixels = _PacedPixels(c_pos, c_neg, reference + c_pos, reference - c_neg, np.full(n_pixels, -np.inf),
                                       float(refractory_us))
    else:
        pixels = _Pixels(c_pos, c_neg, (reference + c_pos).astype(np.float32), (reference - c_neg).astype(np.float32),
                         np.full(n_pixels, np.inf), float(refractory_us))

    t_prev, m_prev = float(t0_us), l_start
    log_render_pixels = None if render_pixels is None else partial(_log_pixels, render_pixels, eps=eps)

    for times, block in _adaptive_blocks(log_render, log_render_pixels, float(t0_us), float(t1_us), l_start, max_dlog,
                                         float(initial_dt_us), float(min_dt_us), int(chunk_samples),
                                         sample_times_us):
        if leak_hz > 0:
            block += leak_per_us * (times - t0_us)[:, None]
        pix, t, pol = pixels.advance(t_prev, m_prev, times, block)
        if shot_noise_hz > 0:
            s_pix, s_t, s_pol = _shot_noise(rng_shot, shot_noise_hz, n_pixels, t_prev, float(times[-1]))
            pix, t, pol = np.concatenate((pix, s_pix)), np.concatenate((t, s_t)), np.concatenate((pol, s_pol))
        t_prev, m_prev = float(times[-1]), block[-1]
        if len(t):
            yield _sorted_chunk(pix, t, pol, width, n_pixels)
