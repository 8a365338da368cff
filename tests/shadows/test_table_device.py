"""The device copy of a shadow mask's lookups (``table_device.DeviceShadowMask``) held to the host's
(``base.ShadowMask``): intervals that wrap, overlap, touch or cover the whole period, pixels without
any, cells shared by several frame pixels, times over several periods and on the intervals' ends, in
batches smaller than the queries. Through torch on the CPU, and on a GPU under ``-m cuda``."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pstoolkit.shadows import table_device
from pstoolkit.shadows.base import ShadowMask
from pstoolkit.shadows.intervals import ShadowIntervals
from pstoolkit.shadows.table_device import DeviceShadowMask

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.cuda)]
PERIOD_US = 1000.0
T0_US = 12345.5
CELLS = 60


def _mask() -> ShadowMask:
    """Shadows of CELLS cells, frame pixels mapped onto them two by two (an event-resolution mask)."""
    rng = np.random.default_rng(3)
    owners = rng.choice(CELLS - 10, 150)  # the last ten cells are never shadowed
    t0 = rng.uniform(0.0, PERIOD_US, owners.size)
    t1 = np.mod(t0 + rng.uniform(1.0, 120.0, owners.size), PERIOD_US)  # some wrap past the period's end
    t0[:3], t1[:3] = 100.0, 100.0 + PERIOD_US  # one a whole period long
    t0[3:5], t1[3:5] = (200.0, 250.0), (250.0, 300.0)  # two that touch
    intervals = ShadowIntervals(owners, t0, t1)
    return ShadowMask.from_intervals(intervals, np.repeat(np.arange(CELLS), 2), T0_US, PERIOD_US)


def _queries(mask: ShadowMask, n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    pixel = rng.integers(0, 2 * CELLS, n)
    t0 = T0_US + rng.uniform(-3 * PERIOD_US, 3 * PERIOD_US, n)
    # a share of the queries on the ends of the table's intervals
    ends = np.concatenate([mask.table.start, mask.table.end])
    on_end = rng.random(n) < 0.2
    key = rng.choice(ends, n)
    cell = np.floor(key / (2 * PERIOD_US)).astype(np.int64)
    pixel = np.where(on_end, 2 * cell, pixel)
    t0 = np.where(on_end, T0_US + key - cell * 2 * PERIOD_US, t0)
    t1 = t0 + rng.uniform(0.0, PERIOD_US, n)
    return pixel, t0, t1


@pytest.mark.parametrize("device", DEVICES)
def test_the_device_mask_answers_as_the_host(device: str, monkeypatch: pytest.MonkeyPatch) -> None:
    mask = _mask()
    monkeypatch.setattr(table_device, "BATCH_BYTES", 700 * table_device._QUERY_BYTES)
    there = DeviceShadowMask(mask, device)
    assert len(there) == len(mask) > 100
    pixel, t0, t1 = _queries(mask, 5000, 4)
    on = {name: torch.as_tensor(a, device=device) for name, a in (("pixel", pixel), ("t0", t0), ("t1", t1))}
    contains = mask.contains(pixel, t0)
    assert 0.2 < contains.mean() < 0.8
    np.testing.assert_array_equal(there.contains(on["pixel"], on["t0"]).cpu().numpy(), contains)
    shadowed = mask.shadowed_us(pixel, t0, t1)
    assert np.any(shadowed == 0) and np.any(shadowed > 0)
    # the same float64 expressions: equal but for an FMA a GPU's compiler may fuse
    np.testing.assert_allclose(there.shadowed_us(on["pixel"], on["t0"], on["t1"]).cpu().numpy(), shadowed, rtol=0, atol=1e-9)
    t = t0[:30]
    grid = mask.contains_grid(pixel[:300], t)
    np.testing.assert_array_equal(there.contains_grid(on["pixel"][:300], on["t0"][:30]).cpu().numpy(), grid)
    overlap = mask.shadowed_grid(pixel[:300], t, t1[:30])
    assert overlap.shape == (30, 300) and np.any(overlap > 0)
    np.testing.assert_allclose(there.shadowed_grid(on["pixel"][:300], on["t0"][:30], on["t1"][:30]).cpu().numpy(), overlap,
                               rtol=0, atol=1e-9)


@pytest.mark.parametrize("device", DEVICES)
def test_a_mask_without_shadows_answers_none_on_the_device(device: str) -> None:
    there = DeviceShadowMask(ShadowMask.none(8, T0_US, PERIOD_US), device)
    pixel = torch.arange(8, device=device)
    t = torch.full((8,), T0_US + 10.0, dtype=torch.float64, device=device)
    assert len(there) == 0
    assert not there.contains(pixel, t).any()
    assert not there.shadowed_us(pixel, t, t + 500.0).any()
    assert there.shadowed_grid(pixel, t[:3], t[:3] + 500.0).shape == (3, 8)
    assert not there.shadowed_grid(pixel, t[:3], t[:3] + 500.0).any()
