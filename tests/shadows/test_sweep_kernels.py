"""The sweep's compiled kernels against numpy's plain statement of what they compute, the edge
tracker that uses them against the shadowed share of each super pixel, computed whole, and the
parallel search of the shadow tables against numpy's."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from pstoolkit.shadows.edge_tracking import SHARE_THRESHOLD, EdgeTracker, SuperPixels
from pstoolkit.shadows.intervals import PARALLEL_SEARCH, search_sorted
from pstoolkit.shadows.sweep_kernels import reached, shadowed_columns


def test_shadowed_columns_compare_the_masked_pixels_margins() -> None:
    rng = np.random.default_rng(3)
    margin = rng.normal(0.2, 0.1, (7, 40 * 30)).astype(np.float32)
    inside = np.flatnonzero(rng.random(40 * 30) < 0.6)
    out = np.empty((7, inside.size), dtype=bool)
    shadowed_columns(margin, 0.225, inside, out)
    np.testing.assert_array_equal(out, margin[:, inside] > np.float32(0.225))
    assert 0 < np.count_nonzero(out) < out.size


def test_reached_counts_each_groups_ones() -> None:
    rng = np.random.default_rng(4)
    block = (rng.random((9, 500)) < 0.4).astype(np.uint8)
    group = rng.integers(0, 37, 500).astype(np.int32)
    needed = rng.integers(0, 8, 37).astype(np.int32)
    out = np.empty((9, 37), dtype=bool)
    reached(block, group, needed, out)
    counts = np.zeros((9, 37), dtype=np.int64)
    for c in range(500):
        counts[:, group[c]] += block[:, c]
    np.testing.assert_array_equal(out, counts >= needed)
    assert 0 < np.count_nonzero(out) < out.size


@pytest.mark.parametrize("block_rows", [1, 5, 64])
def test_the_tracker_finds_where_each_super_pixels_share_crosses_the_threshold(block_rows: int) -> None:
    rng = np.random.default_rng(5)
    covering = np.repeat(np.arange(10, 40), rng.integers(1, 9, 30))
    steps = 64
    # shadows that come and go slowly, so that shares cross the threshold a few times a period
    phase = rng.random(covering.size) * 2 * np.pi
    shadows = np.sin(np.linspace(0, 6 * np.pi, steps, endpoint=False)[:, None] + phase) > 0.3
    groups = SuperPixels.of(SimpleNamespace(super_pixel=covering, mask=np.ones(covering.size, dtype=bool)))  # type: ignore[arg-type]
    tracker = EdgeTracker(groups, count_pixels=True)
    for start in range(0, steps, block_rows):
        tracker.feed(shadows[start : start + block_rows])
    bins, pixel, entering = tracker.edges()

    share = np.stack([shadows[:, covering == p].mean(axis=1) for p in groups.used], axis=1)
    state = share >= SHARE_THRESHOLD - 1e-12
    change = state != np.roll(state, 1, axis=0)
    expected = sorted(zip(*np.nonzero(change)))
    found = sorted((int(b), int(np.searchsorted(groups.used, p))) for b, p in zip(bins, pixel))
    assert found == [(int(k), int(e)) for k, e in expected] and len(found) > 30
    np.testing.assert_array_equal(entering, state[bins, np.searchsorted(groups.used, pixel)])
    np.testing.assert_array_equal(tracker.pixel_bins, shadows.sum(axis=0))



@pytest.mark.parametrize("side", ["left", "right"])
def test_the_parallel_search_gives_numpys_indices(side: str) -> None:
    """``intervals.search_sorted`` (``interval_kernels.sorted_slots`` past PARALLEL_SEARCH queries): the
    indices of ``numpy.searchsorted``, ties and both ends included, for any shape of queries."""
    rng = np.random.default_rng(5)
    keys = np.sort(np.round(rng.uniform(0.0, 1000.0, 3000), 1))
    values = np.round(rng.uniform(-10.0, 1010.0, (PARALLEL_SEARCH // 50, 60)), 1)
    values[0, :5] = [keys[0], keys[-1], keys[7], -1e9, 1e9]
    found = search_sorted(keys, values, side)
    assert values.size >= PARALLEL_SEARCH and found.shape == values.shape
    np.testing.assert_array_equal(found, np.searchsorted(keys, values, side=side))
    np.testing.assert_array_equal(search_sorted(keys, values[:2], side), np.searchsorted(keys, values[:2], side=side))
