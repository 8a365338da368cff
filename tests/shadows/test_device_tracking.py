"""The device copies of the swept shadows' bookkeeping (``device_tracking``) held to the host's: the
same runs in the same order and the same super-pixel edges and pixel counts, for maps fed in blocks
of uneven lengths, runs open at the start and the end and across the period. Through torch on the CPU,
and on a GPU under ``-m cuda``."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pstoolkit.shadows.device_tracking import DeviceEdgeTracker, DeviceRunCollector, edge_tracker, run_collector
from pstoolkit.shadows.edge_tracking import EdgeTracker, SuperPixels
from pstoolkit.shadows.intervals import RunCollector

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.cuda)]


def _map(steps: int, columns: int, seed: int) -> np.ndarray:
    """(steps, columns) bool runs: random lengths, some columns always or never shadowed."""
    rng = np.random.default_rng(seed)
    flips = rng.random((steps, columns)) < 0.08
    shadowed = (np.cumsum(flips, axis=0) + rng.integers(0, 2, columns)) % 2 == 1
    shadowed[:, :3] = True
    shadowed[:, 3:6] = False
    return shadowed


def _blocks(steps: int) -> list[slice]:
    cuts = [0, 1, 2, 9, 40, 41, 100, steps]
    return [slice(a, b) for a, b in zip(cuts[:-1], cuts[1:], strict=True)]


@pytest.mark.parametrize("device", DEVICES)
def test_the_device_collector_gives_the_hosts_runs(device: str) -> None:
    shadowed = _map(120, 300, 0)
    host, there = RunCollector(300), DeviceRunCollector(300, device)
    for part in _blocks(120):
        host.feed(shadowed[part])
        there.feed(torch.as_tensor(shadowed[part], device=device))
    names = np.arange(300) * 7 + 5
    expected, got = host.intervals(1000.0, names), there.intervals(1000.0, names)
    assert len(expected) > 500
    for field in ("pixel", "t0_us", "t1_us"):
        np.testing.assert_array_equal(getattr(got, field), getattr(expected, field))
    empty = DeviceRunCollector(4, device).intervals(1000.0)
    assert len(empty) == 0


@pytest.mark.parametrize("device", DEVICES)
def test_the_device_collector_gives_back_the_map_it_was_fed_at_any_columns(device: str) -> None:
    shadowed = _map(120, 300, 3)
    there = DeviceRunCollector(300, device)
    for part in _blocks(120):
        there.feed(torch.as_tensor(shadowed[part], device=device))
    # always and never shadowed columns among them, out of order
    columns = np.r_[np.random.default_rng(4).permutation(300)[:150], 1, 4]
    grid = there.grid_at(torch.as_tensor(columns, device=device))
    assert grid.dtype == torch.bool and grid.shape == (120, columns.size)
    np.testing.assert_array_equal(grid.cpu().numpy(), shadowed[:, columns])
    assert there.grid_at(torch.empty(0, dtype=torch.int64, device=device)).shape == (120, 0)


@pytest.mark.parametrize("device", DEVICES)
def test_the_device_tracker_gives_the_hosts_edges(device: str) -> None:
    rng = np.random.default_rng(1)
    shadowed = _map(120, 400, 2)
    covering = np.sort(rng.integers(0, 90, 400))
    used, group = np.unique(covering, return_inverse=True)
    groups = SuperPixels(used, group.astype(np.int32), rng.integers(1, 4, used.size).astype(np.int32))
    host, there = EdgeTracker(groups, count_pixels=True), DeviceEdgeTracker(groups, device, count_pixels=True)
    for part in _blocks(120):
        host.feed(shadowed[part])
        there.feed(torch.as_tensor(shadowed[part], device=device))
    expected, got = host.edges(), there.edges()
    assert expected[0].size > 300 and np.any(expected[0] == 0)
    for a, b in zip(got, expected, strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(there.pixel_bins, host.pixel_bins)
    assert there.steps == host.steps == 120
    assert DeviceEdgeTracker(groups, device).pixel_bins is None
    assert DeviceEdgeTracker(groups, device).edges()[0].size == 0
    # every tracker of the same super pixels takes the copies the first one moved there
    assert DeviceEdgeTracker(groups, device).group is there.group and list(groups.there) == [str(torch.device(device))]


def test_the_host_or_the_device_copy_is_picked_by_the_device() -> None:
    groups = SuperPixels(np.arange(2), np.array([0, 1], dtype=np.int32), np.ones(2, dtype=np.int32))
    assert type(run_collector(3, "cpu")) is RunCollector and type(edge_tracker(groups, "cpu")) is EdgeTracker
    assert type(run_collector(3, "meta")) is DeviceRunCollector
    assert type(edge_tracker(groups, "meta")) is DeviceEdgeTracker
