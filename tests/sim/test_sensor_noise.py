"""The sensors' non-idealities (``pstoolkit.sim.sensor``, ``pstoolkit.sim.event_noise``) in both event
engines: leak rate, hot pixels, per-polarity thresholds, seeds, the event order; the frame sensor's
noise and quantisation; the presets from the CLI and what a capture records of them."""

from __future__ import annotations

from dataclasses import replace
from functools import partial
from pathlib import Path

import h5py
import numpy as np
import pytest

import psfmt
from psfmt import EventArray
from pstoolkit.cli import main
from pstoolkit.errors import UserError
from pstoolkit.optics.brdf import GGX, Lambertian
from pstoolkit.optics.lights import RingLight
from pstoolkit.plugin.options import defaults
from pstoolkit.sim import ring_engine
from pstoolkit.sim.config import SimulationConfig
from pstoolkit.sim.esim import simulate_events
from pstoolkit.sim.render import Renderer
from pstoolkit.sim.scenes import Blobs, Sphere
from pstoolkit.sim.sensor import SHOT_NOISE_BRIGHT_FACTOR, EventSensor, FrameSensor, sensor_preset
from pstoolkit.sim.simulator import simulate

PERIOD_US = 30_000.0
SIZE = 32  # frame pixels; events at half that


def flat(period_us: float) -> Renderer:
    """A plane facing the camera under the ring light: its irradiance does not change as the light
    turns (once in ``period_us``: the ring engine's blocks of time are a share of a turn)."""
    maps = Blobs().build(SIZE, 0, **{**defaults(Blobs.options), "height": 0.0, "albedo": "white"})
    return Renderer(maps, RingLight(elevation_deg=45.0, period_us=period_us), Lambertian(), shadows=False)


def sphere() -> Renderer:
    maps = Sphere().build(SIZE, 0, **{**defaults(Sphere.options), "radius": 0.6})
    return Renderer(maps, RingLight(elevation_deg=40.0, period_us=PERIOD_US), GGX(), shadows=False)


def ring(r: Renderer, sensor: EventSensor, t1_us: float) -> EventArray:
    blocks = ring_engine.simulate_ring(r, event_scale=0.5, t1_us=t1_us, window_ends_us=[t1_us], sensor=sensor)
    return EventArray.concatenate([b.events for b in blocks])


def esim(r: Renderer, sensor: EventSensor, t1_us: float) -> EventArray:
    chunks = list(simulate_events(partial(r.event_grey, event_scale=0.5), 0, t1_us, width=SIZE // 2, height=SIZE // 2,
                                  sensor=sensor, initial_dt_us=1000.0, min_dt_us=20.0,
                                  render_pixels=partial(r.event_pixels, event_scale=0.5)))
    for a, b in zip(chunks[:-1], chunks[1:]):
        assert a.t[-1] <= b.t[0]
    return EventArray.concatenate(chunks)


ENGINES = {"ring": ring, "esim": esim}


def counts(events: EventArray, polarity: int | None = None) -> np.ndarray:
    keep = np.ones(len(events), bool) if polarity is None else events.p == polarity
    pixel = events.y[keep].astype(np.int64) * (SIZE // 2) + events.x[keep]
    return np.bincount(pixel, minlength=(SIZE // 2) ** 2)


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize(("refractory_us", "rule"), [(0.0, "reset-at-end"), (2000.0, "reset-at-end"), (4000.0, "rate-limited")])
def test_a_static_scene_leaks_at_the_configured_rate(engine: str, refractory_us: float, rule: str) -> None:
    """Leak events are +1 crossings of a reference that drifts by C⁺ every 1/rate: every pixel fires
    ⌊T·rate⌋ or ⌊T·rate⌋ + 1 of them (its start is random), 1/rate + R apart under "reset-at-end"."""
    rate_hz, t1_us = 40.0, 250_000.0
    sensor = EventSensor(leak_hz=rate_hz, refractory_us=refractory_us, refractory_rule=rule, seed=3)
    events = ENGINES[engine](flat(t1_us), sensor, t1_us)
    assert np.all(events.p == 1) and np.all(np.diff(events.t) >= 0)
    spacing_us = 1e6 / rate_hz + (refractory_us if rule == "reset-at-end" else 0.0)
    per_pixel = counts(events)
    expected = t1_us / spacing_us
    assert per_pixel.min() >= np.floor(expected) and per_pixel.max() <= np.floor(expected) + 1
    assert abs(per_pixel.mean() - expected) < 0.1 * expected
    order = np.lexsort((events.t, events.y.astype(np.int64) * SIZE + events.x))
    t, pixel = events.t[order], (events.y.astype(np.int64) * SIZE + events.x)[order]
    gaps = np.diff(t)[np.diff(pixel) == 0]
    assert np.abs(gaps - spacing_us).max() <= 2


def test_unlit_pixels_leak_alike_in_both_engines() -> None:
    """The ring engine never steps event pixels over no frame pixel; they leak in closed form, as the
    reference engine's black pixels do."""
    r = sphere()
    sensor = EventSensor(leak_hz=200.0, seed=4)
    a, b = ring(r, sensor, 2 * PERIOD_US), esim(r, sensor, 2 * PERIOD_US)
    unlit = ~r.maps.mask.reshape(SIZE // 2, 2, SIZE // 2, 2).any(axis=(1, 3)).reshape(-1)
    assert unlit.sum() > 20
    assert np.array_equal(counts(a)[unlit], counts(b)[unlit])
    assert np.all((counts(a)[unlit] >= 11) & (counts(a)[unlit] <= 12))


@pytest.mark.parametrize("engine", ENGINES)
def test_hot_pixels_fire_at_their_rate_outside_their_dead_time(engine: str) -> None:
    """A hot pixel is a Poisson process of its rate λ thinned by the refractory period R
    (non-paralysable): λ/(1 + λR) events per second, none closer than R."""
    rate_hz, refractory_us, t1_us = 400.0, 1000.0, 300_000.0
    sensor = EventSensor(hot_pixel_fraction=0.1, hot_pixel_hz=rate_hz, refractory_us=refractory_us, seed=5)
    events = ENGINES[engine](flat(t1_us), sensor, t1_us)
    per_pixel = counts(events)
    hot = per_pixel > 0
    assert 10 <= hot.sum() <= 45
    expected = rate_hz / (1 + rate_hz * refractory_us * 1e-6) * t1_us * 1e-6 * hot.sum()
    assert abs(per_pixel.sum() - expected) < 4 * np.sqrt(expected)
    assert abs(np.mean(events.p == 1) - 0.5) < 0.05
    order = np.lexsort((events.t, events.y.astype(np.int64) * SIZE + events.x))
    pixel = (events.y.astype(np.int64) * SIZE + events.x)[order]
    assert np.diff(events.t[order])[np.diff(pixel) == 0].min() >= refractory_us


@pytest.mark.parametrize("engine", ENGINES)
def test_shot_noise_is_a_poisson_rate_that_rises_in_the_dark(engine: str) -> None:
    """On the lit plane (irradiance ``I`` ≤ 1 everywhere) the shot-noise rate is the dark rate times
    1 − (1 − SHOT_NOISE_BRIGHT_FACTOR)·I."""
    rate_hz, t1_us = 300.0, 200_000.0
    r = flat(t1_us)
    grey = r.event_grey(np.array([0.0]), 0.5)[0].reshape(-1)
    assert 0.3 < grey.min() and grey.max() < 1.0
    events = ENGINES[engine](r, EventSensor(shot_noise_hz=rate_hz, seed=6), t1_us)
    expected = float(np.sum(rate_hz * (1 - (1 - SHOT_NOISE_BRIGHT_FACTOR) * grey))) * t1_us * 1e-6
    assert abs(len(events) - expected) < 4 * np.sqrt(expected)
    assert abs(np.mean(events.p == 1) - 0.5) < 0.05


@pytest.mark.parametrize("engine", ENGINES)
def test_per_polarity_thresholds_set_the_on_off_ratio(engine: str) -> None:
    """Over whole turns L returns to its start, so each pixel's rises and falls cancel: its ON and OFF
    counts satisfy |N⁺·C⁺ − N⁻·C⁻| ≤ max(C⁺, C⁻), and over the sensor N⁺/N⁻ ≈ C⁻/C⁺."""
    c_pos, c_neg = 0.1, 0.25
    r = Renderer(Blobs().build(SIZE, 0, **defaults(Blobs.options)), RingLight(elevation_deg=40.0, period_us=PERIOD_US), Lambertian(),
                 shadows=False)
    events = ENGINES[engine](r, EventSensor(c_pos, c_neg), PERIOD_US)
    on, off = counts(events, 1), counts(events, -1)
    assert on.sum() > 500
    assert np.abs(on * c_pos - off * c_neg).max() <= max(c_pos, c_neg) + 1e-3
    assert abs(on.sum() / off.sum() / (c_neg / c_pos) - 1) < 0.1


NOISY = EventSensor(contrast_pos=0.2, contrast_neg=0.25, sigma=0.03, refractory_us=500.0, refractory_rule="rate-limited",
                    leak_hz=20.0, shot_noise_hz=100.0, rate_spread_decades=0.2, hot_pixel_fraction=0.05, hot_pixel_hz=500.0)


@pytest.mark.parametrize("engine", ENGINES)
def test_the_same_seed_gives_the_same_events_a_different_seed_others(engine: str) -> None:
    r = flat(PERIOD_US)
    first, again, other = (ENGINES[engine](r, replace(NOISY, seed=s), PERIOD_US) for s in (7, 7, 8))
    assert all(np.array_equal(getattr(first, k), getattr(again, k)) for k in "xytp")
    assert len(first) != len(other) or not np.array_equal(first.t, other.t)
    assert np.all(np.diff(first.t) >= 0)


def test_bad_noise_figures_name_the_field() -> None:
    with pytest.raises(UserError, match="simulate_events: hot_pixel_fraction must be between 0 and 1, got 1.5"):
        list(simulate_events(lambda t: np.ones((len(t), 2, 2)), 0, 10, width=2, height=2,
                             sensor=EventSensor(hot_pixel_fraction=1.5)))
    with pytest.raises(UserError, match="simulate_ring: leak_hz must be zero or positive, got -1.0"):
        ring(flat(PERIOD_US), EventSensor(leak_hz=-1.0), PERIOD_US)


def test_frame_noise_has_the_model_s_mean_and_spread() -> None:
    """Shot noise of ``e`` electrons and read noise ``r``: std √(e + r²) electrons, in stored units
    ×(saturation − black)/full well, around black + signal."""
    sensor = FrameSensor(bit_depth=12, black_level=64.0, full_well_e=10_000.0, read_noise_e=20.0)
    signal = 1500.0
    values = sensor.quantise(np.full(200_000, signal), np.random.default_rng(0)).astype(np.float64)
    per_electron = (4095 - 64) / 10_000.0
    electrons = signal / per_electron
    assert values.dtype == np.float64 and abs(values.mean() - (64 + signal)) < 0.5
    assert abs(values.std() / (np.sqrt(electrons + 20.0**2) * per_electron) - 1) < 0.02
    ideal = FrameSensor(bit_depth=12, black_level=64.0).quantise(np.array([-5.0, 0.0, 100.4, 5000.0]), np.random.default_rng(0))
    assert ideal.dtype == np.uint16 and ideal.tolist() == [59, 64, 164, 4095]


def test_presets_from_the_cli_are_recorded_and_round_trip(tmp_path: Path) -> None:
    """12-bit frames with a black level and noise, the sensor model in /calibration; a field given on
    the command line overrides the preset's and the model is marked modified."""
    out = tmp_path / "evk4.h5"
    assert main(["simulate", "sphere", "--size", "32", "--sensor", "evk4", "--device", "cpu", "-o", str(out), "-q"]) == 0
    assert [f"{e.where}: {e.message}" for e in psfmt.validate(out).errors] == []
    preset = sensor_preset("evk4")
    with psfmt.read(out) as capture:
        frames, calibration = capture.frames, capture.calibration
        assert (frames.bit_depth, frames.black_level, frames.saturation, frames.data.dtype) == (12, 64.0, 4095.0, np.uint16)
        background = frames.data[0][~capture.ground_truth.mask]
        # black background: the black level, read noise of 2.4 e⁻ (0.93 stored units)
        assert abs(background.astype(np.float64).mean() - 64.0) < 0.5 and background.std() < 2.0
        assert calibration.contrast_pos == calibration.contrast_neg == preset.event.contrast_pos
        assert calibration.refractory_rule == "rate-limited" and calibration.refractory_us == 500.0
        assert calibration.sensor_model == {**preset.record(), "name": "evk4"}
    with h5py.File(out, "r+") as f:
        f["calibration"].attrs["leak_hz"] = -1.0
        f["calibration"].attrs["hot_pixel_fraction"] = 2.0
        f["calibration"].attrs["sensor_model"] = 3
    assert [f"{e.where}: {e.message}" for e in psfmt.validate(out).errors] == [
        "/calibration: sensor_model must be a string, got 3",
        "/calibration: leak_hz must be a finite number ≥ 0, got -1.0",
        "/calibration: hot_pixel_fraction must be a finite number between 0 and 1, got 2.0",
    ]
    modified = tmp_path / "davis.h5"
    assert main(["simulate", "blobs", "--size", "32", "--sensor", "davis346", "--contrast-neg", "0.3", "--leak-hz", "2",
                 "--device", "cpu", "-o", str(modified), "-q"]) == 0
    with psfmt.read(modified) as capture:
        model = capture.calibration.sensor_model
        assert model["name"] == "davis346 (modified)" and model["leak_hz"] == 2.0
        assert capture.calibration.contrast_neg == 0.3 and capture.calibration.contrast_pos == sensor_preset("davis346").event.contrast_pos
        assert capture.frames.bit_depth == 10


def test_the_ideal_preset_is_today_s_simulator(tmp_path: Path) -> None:
    """--sensor ideal writes the frames and events of the simulator's defaults, through the engine
    with no noise source."""
    a, b = tmp_path / "a.h5", tmp_path / "b.h5"
    assert main(["simulate", "blobs", "--size", "32", "--sensor", "ideal", "--device", "cpu", "-o", str(a), "-q"]) == 0
    simulate(SimulationConfig(scene="blobs", size=32), b)
    with psfmt.read(a) as x, psfmt.read(b) as y:
        assert np.array_equal(x.frames.data[:], y.frames.data[:]) and x.frames.data.dtype == np.uint8
        ex, ey = x.events.read(), y.events.read()
        assert len(ex) > 500 and all(np.array_equal(getattr(ex, k), getattr(ey, k)) for k in "xytp")
        assert x.calibration.sensor_model == {"name": "ideal", **{k: 0.0 for k in x.calibration.sensor_model if k != "name"}}
