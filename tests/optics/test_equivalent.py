"""Equivalent lights: midpoint rule vs the ring's closed form, shadow clamp vs a dense sum, visibility."""

from __future__ import annotations

import numpy as np
import pytest

from pstoolkit.optics import equivalent
from pstoolkit.optics.equivalent import DEFAULT_SAMPLES, equivalent_lights, sample_times
from pstoolkit.optics.lights import NearRingLight, RingLight, SampledLight

PERIOD_US = 33333.0


def _ring(**kwargs) -> RingLight:
    params = dict(elevation_deg=35.0, period_us=PERIOD_US, phase_deg=20.0, sense=-1, intensity=(1.0, 0.5, 2.0))
    params.update(kwargs)
    return RingLight(**params)


def test_sample_times_midpoints() -> None:
    np.testing.assert_allclose(sample_times(100, 200, 4), [112.5, 137.5, 162.5, 187.5])
    with pytest.raises(ValueError, match="empty"):
        sample_times(5, 5, 3)


@pytest.mark.parametrize(
    ("t0", "t1"),
    [(0.0, PERIOD_US / 3), (PERIOD_US / 3, 2 * PERIOD_US / 3), (1234.0, 1234.0 + PERIOD_US / 2), (500.0, 500.0 + 1.3 * PERIOD_US), (0.0, PERIOD_US)],
)
def test_midpoint_default_within_0p1_percent_of_closed_form(t0: float, t1: float) -> None:
    light = _ring()
    got = equivalent_lights(light, t0, t1)
    want = np.array([1.0, 0.5, 2.0])[:, None] * light.integral(t0, t1)[None, :]
    assert got.shape == (3, 3)
    assert np.linalg.norm(got - want) <= 1e-3 * np.linalg.norm(want)


def test_closed_form_matches_a_dense_sum_and_is_additive() -> None:
    light = _ring(elevation_deg=10.0, sense=1)
    t = sample_times(300.0, 20000.0, 200000)
    dense = light.evaluate(t)[0].sum(axis=0) * (19700.0 / 200000) / 1e6
    np.testing.assert_allclose(light.integral(300.0, 20000.0), dense, rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(light.integral(0.0, 5000.0) + light.integral(5000.0, 9000.0), light.integral(0.0, 9000.0), atol=1e-15)


def test_attached_shadow_clamp_equals_dense_sum() -> None:
    light = _ring(elevation_deg=20.0)
    normals = np.array([[0.0, 0.0, 1.0], [0.9, 0.0, np.sqrt(1 - 0.81)], [-0.5, 0.8, np.sqrt(1 - 0.89)], [0.0, -1.0, 0.0]])
    t0, t1 = 0.0, PERIOD_US / 3
    t = sample_times(t0, t1, 100000)
    direction, intensity = light.evaluate(t)
    lit = (direction @ normals.T > 0).astype(np.float64)  # (T, P)
    dense = np.einsum("tp,tc,tx->pcx", lit, intensity, direction) * ((t1 - t0) / 100000 / 1e6)
    got = equivalent_lights(light, t0, t1, n_samples=2048, normals=normals)
    assert got.shape == (4, 3, 3)
    np.testing.assert_allclose(got, dense, atol=2e-3 * np.abs(dense).max())
    # A normal facing the camera never sees the ring from behind: the clamp changes nothing.
    np.testing.assert_allclose(got[0], equivalent_lights(light, t0, t1, n_samples=2048), rtol=1e-12)
    # The grazing normal is lit for part of the window only, so the clamp must have removed something.
    assert np.linalg.norm(got[3]) < 0.9 * np.linalg.norm(got[0])


def test_visibility_zeroing_half_the_window_keeps_the_other_half() -> None:
    light = _ring()
    t0, t1, n = 1000.0, 1000.0 + PERIOD_US / 3, 256
    visibility = np.ones((n, 2), dtype=bool)
    visibility[n // 2 :, 1] = False
    got = equivalent_lights(light, t0, t1, visibility=visibility)
    middle = (t0 + t1) / 2
    full = np.array([1.0, 0.5, 2.0])[:, None] * light.integral(t0, t1)
    first_half = np.array([1.0, 0.5, 2.0])[:, None] * light.integral(t0, middle)
    np.testing.assert_allclose(got[0], full, rtol=1e-4)
    np.testing.assert_allclose(got[1], first_half, rtol=1e-4)
    with pytest.raises(ValueError, match="visibility holds 256 sample times, n_samples is 64"):
        equivalent_lights(light, t0, t1, visibility=visibility, n_samples=64)


def test_pixel_batch_shape_and_chunking(monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(0)
    normals = rng.normal(size=(6, 7, 3))
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    light = _ring()
    whole = equivalent_lights(light, 0.0, 9000.0, normals=normals)
    assert whole.shape == (6, 7, 3, 3)
    monkeypatch.setattr(equivalent, "CHUNK_VALUES", 3 * DEFAULT_SAMPLES * 5)  # 5 pixels per chunk
    # chunks change the order of the sums (and the SIMD kernels numpy picks per CPU): equal to rounding,
    # far below the 1e-4 relative error a chunk that lost or repeated pixels would make
    chunked = equivalent_lights(light, 0.0, 9000.0, normals=normals)
    np.testing.assert_allclose(chunked, whole, rtol=1e-12, atol=1e-12 * np.abs(whole).max())


def test_sampled_light_with_varying_intensity() -> None:
    light = SampledLight([0, 1000], [[0, 0, 1], [0, 0, 1]], [[0, 0, 0], [2, 4, 6]])
    got = equivalent_lights(light, 0.0, 1000.0)
    # ∫ (2t/T) dt over [0, T] with T = 1 ms is 1 ms · 1 = 1e-3 s for the red channel.
    np.testing.assert_allclose(got, [[0, 0, 1e-3], [0, 0, 2e-3], [0, 0, 3e-3]], atol=1e-15)


def test_near_light_per_pixel_and_clamp() -> None:
    near = NearRingLight(radius_mm=50, height_mm=50, pixel_pitch_mm=1.0, period_us=PERIOD_US)
    points = near.pixel_points(3, 3)
    got = equivalent_lights(near, 0.0, PERIOD_US, points_mm=points)
    assert got.shape == (9, 3, 3)
    # At the ring centre a full turn leaves only z: ∫ sin(45°) dt with unit intensity.
    np.testing.assert_allclose(got[4, 0], [0, 0, np.sqrt(0.5) * PERIOD_US / 1e6], atol=1e-12)
    # Off-centre the light comes from the nearer side of the ring on average.
    assert got[5, 0, 0] < 0 and got[3, 0, 0] > 0
    shadowed = equivalent_lights(near, 0.0, PERIOD_US, points_mm=points, normals=np.tile([1.0, 0, 0], (9, 1)))
    assert np.all(shadowed[:, 0, 0] > 0)
    with pytest.raises(ValueError, match="near light: pass points_mm"):
        equivalent_lights(near, 0.0, 10.0)
