"""Adaptive sampling of the reference event engine (``pstoolkit.sim.esim``): blocks of render times
whose intervals change no pixel's ``L`` by more than ``max_dlog``, refined whole-frame or per pixel
(see the ``Sampling`` and ``Per-pixel refinement`` items of that module's docstring)."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator

import numpy as np

RenderPixels = Callable[[np.ndarray, np.ndarray], np.ndarray]
# Shares of the sensor's pixels needing refinement in one interval above / below which the step of
# full renders is halved / doubled when pixels can be rendered alone (``render_pixels``): full
# renders are cheaper per pixel, so they should carry all but a few per cent of the pixels.
REFINE_SHARE_HIGH = 0.02
REFINE_SHARE_LOW = 0.002

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


def adaptive_blocks(
    log_render: Callable[[np.ndarray], np.ndarray], log_render_pixels: RenderPixels | None, t0_us: float,
    t1_us: float, l_start: np.ndarray, max_dlog: float, initial_dt_us: float, min_dt_us: float, cap: int,
    sample_times_us: np.ndarray | None = None,
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Blocks of sample times and log frames covering (t0_us, t1_us], in order, whose intervals change no
    pixel's L by more than ``max_dlog`` (down to ``min_dt_us``).

    Parameters
    ----------
    log_render
        ``log_render(t_us (n,)) -> (n, H·W)``: the whole frame's L at those times.
    log_render_pixels
        Optional ``log_render_pixels(t_us (M,), pixel (M,)) -> (M,)``: L of single pixels at single times.
        Without it, refinement renders whole frames and the step of the next block follows the mean step
        of this one (refinement included). With it, refinement is per pixel and cheap, so the step of the
        full renders follows the share of pixels that needed refining instead: halved above
        ``REFINE_SHARE_HIGH``, doubled below ``REFINE_SHARE_LOW``; a block then renders at most a quarter
        of ``cap`` full frames, leaving room for the refined samples.
    t0_us, t1_us
        The span sampled, µs.
    l_start
        (H·W,) L at ``t0_us``.
    max_dlog
        Largest change of L allowed in one interval, for any pixel.
    initial_dt_us
        The first step of the full renders, µs.
    min_dt_us
        The shortest interval that is still split, µs.
    cap
        The most samples in one block, refined ones included.
    sample_times_us
        Optional fixed times of the full renders (sorted, ending at ``t1_us``), µs, instead of the
        adaptive steps; refinement still applies.

    Yields
    ------
    times : numpy.ndarray
        (n,) sample times, µs, increasing.
    log_frames : numpy.ndarray
        (n, H·W) L at those times.
    """
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
