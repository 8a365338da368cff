"""Light models: the ring formula, sampled interpolation, the near ring's geometry and spec round trips."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import psfmt
from psfmt import LightSpec
from pstoolkit.errors import UserError
from pstoolkit.optics.lights import LightModel, NearRingLight, RingLight, SampledLight, build_light_model, pixel_points_mm


def test_ring_direction_formula() -> None:
    light = RingLight(elevation_deg=30, period_us=1000, phase_deg=90, sense=1, intensity=(1, 2, 3))
    t = np.array([0, 250, 500, 1000, 1250], dtype=np.int64)
    direction, intensity = light.evaluate(t)
    c, s = np.cos(np.deg2rad(30)), np.sin(np.deg2rad(30))
    expected = np.array([[0, c, s], [-c, 0, s], [0, -c, s], [0, c, s], [-c, 0, s]])
    np.testing.assert_allclose(direction, expected, atol=1e-12)
    np.testing.assert_array_equal(intensity, np.tile([1.0, 2.0, 3.0], (5, 1)))


def test_ring_sense_and_t0() -> None:
    forward = RingLight(elevation_deg=45, period_us=400, sense=1, t0_us=100)
    backward = RingLight(elevation_deg=45, period_us=400, sense=-1, t0_us=100)
    t = np.array([100.0, 200.0])
    d_f, _ = forward.evaluate(t)
    d_b, _ = backward.evaluate(t)
    c = np.cos(np.deg2rad(45))
    np.testing.assert_allclose(d_f[:, :2], [[c, 0], [0, c]], atol=1e-12)
    np.testing.assert_allclose(d_b[:, :2], [[c, 0], [0, -c]], atol=1e-12)


def test_ring_is_periodic_and_precise_at_large_times() -> None:
    light = RingLight(elevation_deg=60, period_us=33333, phase_deg=17, sense=-1)
    t = np.array([1234, 5678], dtype=np.int64)
    later = t + 33333 * 10**6
    np.testing.assert_allclose(light.evaluate(later)[0], light.evaluate(t)[0], atol=1e-12)


def test_directional_broadcasts_over_points() -> None:
    light = RingLight(elevation_deg=45, period_us=100)
    direction, intensity = light.evaluate(np.arange(4.0), np.zeros((5, 3)))
    assert direction.shape == intensity.shape == (4, 5, 3)
    # bit-equal: a directional model broadcasts the same (T, 3) directions over the points (a copy)
    np.testing.assert_array_equal(direction[:, 3], light.evaluate(np.arange(4.0))[0])


def test_sampled_interpolates_and_renormalises() -> None:
    light = SampledLight(
        times_us=[0, 10, 20],
        directions=[[1, 0, 0], [0, 1, 0], [0, 0, 1]],
        intensities=[[1, 1, 1], [3, 5, 7], [1, 1, 1]],
    )
    direction, intensity = light.evaluate(np.array([5.0, 10.0, 12.5]))
    r = 1 / np.sqrt(2)
    np.testing.assert_allclose(direction[0], [r, r, 0], atol=1e-12)
    np.testing.assert_allclose(direction[1], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(direction[2], np.array([0, 0.75, 0.25]) / np.hypot(0.75, 0.25), atol=1e-12)
    np.testing.assert_allclose(intensity, [[2, 3, 4], [3, 5, 7], [2.5, 4, 5.5]], atol=1e-12)


def test_sampled_clamps_when_aperiodic() -> None:
    light = SampledLight([0, 10], [[1, 0, 0], [0, 1, 0]], [[1, 1, 1], [2, 2, 2]])
    direction, intensity = light.evaluate(np.array([-100.0, 100.0]))
    np.testing.assert_allclose(direction, [[1, 0, 0], [0, 1, 0]], atol=1e-12)
    np.testing.assert_allclose(intensity, [[1, 1, 1], [2, 2, 2]])
    assert light.period_us is None


def test_sampled_wraps_when_periodic() -> None:
    light = SampledLight(
        [0, 10], [[1, 0, 0], [0, 1, 0]], [[1, 1, 1], [3, 3, 3]], periodic=True, period_us=30
    )
    # t = 20 is halfway from the last sample (10) to the first sample + period (30).
    direction, intensity = light.evaluate(np.array([20.0, 50.0, -10.0, 35.0]))
    r = 1 / np.sqrt(2)
    np.testing.assert_allclose(direction, [[r, r, 0], [r, r, 0], [r, r, 0], [r, r, 0]], atol=1e-12)
    np.testing.assert_allclose(intensity[:, 0], [2, 2, 2, 2], atol=1e-12)
    assert light.period_us == 30


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (dict(times_us=[0, 0], directions=[[1, 0, 0]] * 2, intensities=[[1, 1, 1]] * 2), "not strictly increasing"),
        (dict(times_us=[0, 1], directions=[[1, 0, 0]], intensities=[[1, 1, 1]] * 2), "differ in length"),
        (dict(times_us=[0, 1], directions=[[1, 0, 0]] * 2, intensities=[[1, 1, 1]] * 2, periodic=True), "needs 'period_us'"),
        (dict(times_us=[0, 5], directions=[[1, 0, 0]] * 2, intensities=[[1, 1, 1]] * 2, periodic=True, period_us=5), "does not exceed"),
        (dict(times_us=[0, 1], directions=[[1, 0, 0], [-1, 0, 0]], intensities=[[1, 1, 1]] * 2), "opposite"),
    ],
)
def test_sampled_rejects_bad_input(kwargs: dict, message: str) -> None:
    with pytest.raises(UserError, match=message):
        SampledLight(**kwargs)


def test_pixel_points_convention() -> None:
    points = pixel_points_mm(3, 5, 0.5).reshape(3, 5, 3)
    np.testing.assert_allclose(points[0, 0], [-1.0, 0.5, 0.0])  # top left: x left of centre, y up
    np.testing.assert_allclose(points[1, 2], [0.0, 0.0, 0.0])
    np.testing.assert_allclose(points[2, 4], [1.0, -0.5, 0.0])
    shifted = pixel_points_mm(3, 5, 2.0, center_px=(0, 0), depth_mm=np.full((3, 5), 7.0)).reshape(3, 5, 3)
    np.testing.assert_allclose(shifted[2, 1], [2.0, -4.0, 7.0])


def test_near_ring_direction_and_inverse_square() -> None:
    light = NearRingLight(radius_mm=30, height_mm=40, pixel_pitch_mm=0.1, period_us=1000, intensity=(2, 2, 2))
    points = np.array([[0.0, 0.0, 0.0], [30.0, 0.0, 0.0], [0.0, 0.0, 20.0]])
    direction, intensity = light.evaluate(np.array([0.0]), points)
    assert direction.shape == intensity.shape == (1, 3, 3)
    np.testing.assert_allclose(direction[0], [[0.6, 0, 0.8], [0, 0, 1], [30 / np.hypot(30, 20), 0, 20 / np.hypot(30, 20)]])
    # (R² + h²) / |P − X|²: 1 at the centre, 2500/1600 under the light, 2500/1300 at z = 20.
    np.testing.assert_allclose(intensity[0, :, 0], [2.0, 2 * 2500 / 1600, 2 * 2500 / 1300])


def test_near_ring_needs_points() -> None:
    light = NearRingLight(radius_mm=30, height_mm=40, pixel_pitch_mm=0.1, period_us=1000)
    with pytest.raises(UserError, match="needs|near light"):
        light.evaluate(np.array([0.0]))


def test_near_ring_approaches_ring_far_away() -> None:
    near = NearRingLight(radius_mm=1e7, height_mm=1e7, pixel_pitch_mm=1.0, period_us=500, phase_deg=30, sense=-1)
    far = RingLight(elevation_deg=45, period_us=500, phase_deg=30, sense=-1)
    t = np.linspace(0, 500, 7)
    d_near, _ = near.evaluate(t, near.pixel_points(4, 4))
    np.testing.assert_allclose(d_near, np.broadcast_to(far.evaluate(t)[0][:, None], d_near.shape), atol=1e-5)


@pytest.mark.parametrize(
    "light",
    [
        RingLight(elevation_deg=40, period_us=33333, phase_deg=12.5, sense=-1, intensity=(1, 0.5, 0.25), t0_us=77),
        SampledLight([0, 5, 9], np.eye(3), [[1, 2, 3], [4, 5, 6], [7, 8, 9]], periodic=True, period_us=12),
        SampledLight([3], [[0, 0, 1]], [[1, 1, 1]]),
        NearRingLight(radius_mm=75, height_mm=70, pixel_pitch_mm=0.05, period_us=20000, center_px=(10.5, 20)),
    ],
)
def test_spec_round_trip(light: LightModel) -> None:
    spec = light.to_spec()
    again = type(light).from_spec(LightSpec(spec.model, dict(spec.params)))
    assert again.to_spec().model == spec.model == light.name
    assert again.to_spec().params.keys() == spec.params.keys()
    for key, value in spec.params.items():
        np.testing.assert_array_equal(again.to_spec().params[key], value)
    t = np.linspace(-3e4, 3e4, 11)
    points = np.array([[1.0, 2.0, 0.0], [-3.0, 0.5, 1.0]])
    # bit-equal: the same parameters (copied, not recomputed) through the same code on the same times
    for got, want in zip(again.evaluate(t, points), light.evaluate(t, points)):
        np.testing.assert_array_equal(got, want)


def test_from_spec_errors_name_the_parameter() -> None:
    with pytest.raises(UserError, match=r"light model 'ring': parameter 'period_us' is missing"):
        RingLight.from_spec(LightSpec("ring", {"elevation_deg": 45, "phase_deg": 0, "sense": 1, "intensity": np.ones(3)}))
    params = {"elevation_deg": 45, "period_us": 10, "phase_deg": 0, "sense": 2, "intensity": np.ones(3)}
    with pytest.raises(UserError, match=r"'sense' must be \+1 or -1, got 2"):
        RingLight.from_spec(LightSpec("ring", params))
    with pytest.raises(UserError, match=r"interpolation 'cubic' is not supported"):
        SampledLight.from_spec(
            LightSpec("sampled", {"times_us": [0], "directions": [[0, 0, 1]], "intensities": [[1, 1, 1]], "periodic": False, "interpolation": "cubic"})
        )
    with pytest.raises(UserError, match=r"'intensity' has shape \(2,\), expected \(3,\)"):
        RingLight(elevation_deg=45, period_us=10, intensity=(1, 1))


def test_build_light_model_uses_the_registry() -> None:
    light = RingLight(elevation_deg=50, period_us=1000, phase_deg=5)
    built = build_light_model(light.to_spec())
    assert isinstance(built, RingLight)
    # bit-equal: the registry builds the same class from the same parameters; the same code runs
    np.testing.assert_array_equal(built.evaluate(np.arange(3.0))[0], light.evaluate(np.arange(3.0))[0])
    assert isinstance(build_light_model(NearRingLight(radius_mm=1, height_mm=1, pixel_pitch_mm=1, period_us=1).to_spec()), NearRingLight)
    with pytest.raises(UserError, match=r"unknown .*'spiral'"):
        build_light_model(LightSpec("spiral", {}))


@pytest.mark.parametrize(
    "light",
    [
        RingLight(elevation_deg=40, period_us=33333, phase_deg=12.5, sense=-1, t0_us=77),
        SampledLight([0, 5, 9], np.eye(3), np.ones((3, 3)), periodic=True, period_us=12),
        NearRingLight(radius_mm=75, height_mm=70, pixel_pitch_mm=0.05, period_us=20000, center_px=(10.5, 20)),
    ],
)
def test_specs_survive_a_capture_file_and_validate(tmp_path: Path, light: LightModel) -> None:
    frames = psfmt.Frames(np.zeros((1, 4, 4, 3), np.float32), t_start_us=np.array([0]), t_end_us=np.array([100]))
    path = tmp_path / "c.h5"
    psfmt.write(psfmt.Capture(frames=frames, lights=light.to_spec()), path)
    assert psfmt.validate(path).errors == []
    with psfmt.read(path) as capture:
        again = build_light_model(capture.lights)
    t = np.linspace(0, 5e4, 9)
    points = np.array([[1.0, 2.0, 0.0]])
    # bit-equal: HDF5 stores the float64 parameters exactly and the same code evaluates them
    np.testing.assert_array_equal(again.evaluate(t, points)[0], light.evaluate(t, points)[0])
