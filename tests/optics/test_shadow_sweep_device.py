"""The device copy of the shadow sweep (``shadow_sweep_device``, what a solver on a GPU marches its
surface with) held to the compiled sweep (``shadow_sweep.ShadowCaster``): the same float32 margins,
bit for bit, for lights all around and at every elevation, overhead and along the axes, on a
non-square map with a mask, in small batches and large. Through torch on the CPU, and on a GPU under
``-m cuda``."""

from __future__ import annotations

import numpy as np
import pytest

import pstoolkit.optics.shadow_sweep_device as sweep_device
from pstoolkit.optics.shadow_sweep import ShadowCaster, cast_shadow_mask
from pstoolkit.optics.shadow_sweep_device import DeviceCaster


def _scene(height: int, width: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A bumpy height map (pixels) with a wall and an oval mask, and 160 light directions: random, four
    along the image axes, one overhead."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:height, 0:width] / max(height, width)
    depth = 20 * np.sin(6 * x) * np.cos(4 * y) + 10 * np.exp(-((x - 0.5) ** 2 + (y - 0.5) ** 2) / 0.02)
    depth += rng.normal(0.0, 0.3, depth.shape)
    depth[:, width // 3] += 15.0
    mask = (x - 0.5) ** 2 + (y - 0.45) ** 2 < 0.2
    azimuth, elevation = rng.uniform(0, 2 * np.pi, 160), rng.uniform(0.02, 1.5, 160)
    directions = np.stack([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)], axis=-1)
    directions[:5] = [[1, 0, 0.3], [0, 1, 0.3], [-1, 0, 0.3], [0, -1, 0.3], [0, 0, 1]]
    return depth, mask, directions / np.linalg.norm(directions, axis=1, keepdims=True)


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.cuda)])
def test_the_margins_are_the_compiled_sweeps(device: str, monkeypatch: pytest.MonkeyPatch) -> None:
    depth, mask, directions = _scene(41, 58, 0)
    host = ShadowCaster(depth, mask).margins(directions)
    there = DeviceCaster(depth, mask, device)
    np.testing.assert_array_equal(there.margins(directions).cpu().numpy(), host)
    # a batch of one light at a time: the same
    monkeypatch.setattr(sweep_device, "BATCH_BYTES", 1)
    np.testing.assert_array_equal(there.margins(directions[:20]).cpu().numpy(), host[:20])
    # and the shadows the simulator draws from them
    shadowed = there.margins(directions[:20]).cpu().numpy() > 0.1 + 0.5 * 0.25
    np.testing.assert_array_equal(shadowed, cast_shadow_mask(depth, mask, directions[:20]))
    assert 0.02 < shadowed[:, mask].mean() < 0.5


def test_no_light_no_shadow() -> None:
    depth, mask, _ = _scene(16, 16, 1)
    out = DeviceCaster(depth, mask, "cpu").margins(np.zeros((0, 3)))
    assert tuple(out.shape) == (0, 16, 16)
