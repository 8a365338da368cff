"""The ESIM-style event generator against analytic irradiance: threshold rule, counts, refractory,
memory bound, noise rates, determinism."""

from __future__ import annotations

import numpy as np
import pytest
from helpers.esim import PERIOD_US, SIZE, C, sine_scene, threshold_residuals

from psfmt import EventArray
from pstoolkit.errors import UserError
from pstoolkit.events.rule import LOG_EPS, consecutive_pairs, log_irradiance
from pstoolkit.sim.esim import simulate_events
from pstoolkit.sim.sensor import SHOT_NOISE_BRIGHT_FACTOR, EventSensor


def run(render, t0: float, t1: float, chunk_samples: int = 64, initial_dt_us: float = 100.0,
        **sensor) -> tuple[EventArray, list[EventArray]]:
    chunks = list(simulate_events(render, t0, t1, width=SIZE, height=SIZE, sensor=EventSensor(**sensor),
                                  chunk_samples=chunk_samples, initial_dt_us=initial_dt_us))
    return EventArray.concatenate(chunks), chunks






@pytest.mark.parametrize("refractory_us", [0.0, 30_000.0])
@pytest.mark.parametrize("static_columns", [0, 12])
def test_every_event_obeys_the_threshold_rule(static_columns: int, refractory_us: float) -> None:
    # With most pixels static, only the few that can fire are stepped: both paths are checked.
    render, *_ = sine_scene(static_columns=static_columns)
    events, _ = run(render, 0, PERIOD_US, refractory_us=refractory_us)
    assert len(events) > 100 * (SIZE - static_columns)
    assert events.x.min() == static_columns
    residual = threshold_residuals(render, events, 0, refractory_us)
    assert np.abs(residual).max() < 2e-3


def test_counts_on_monotonic_stretches() -> None:
    render, albedo, offset, _ = sine_scene()

    def no_phase(t_us: np.ndarray) -> np.ndarray:
        t = np.asarray(t_us, dtype=np.float64)[:, None, None]
        return albedo * (offset + np.sin(2 * np.pi * t / PERIOD_US))

    quarter = PERIOD_US / 4
    for t0, t1, polarity in ((-quarter, quarter, 1), (quarter, 3 * quarter, -1)):
        events, _ = run(no_phase, t0, t1)
        assert set(np.unique(events.p)) == {polarity}
        counts = np.bincount(events.y.astype(np.int64) * SIZE + events.x, minlength=SIZE * SIZE)
        change = np.abs(log_irradiance(no_phase(np.array([t1]))) - log_irradiance(no_phase(np.array([t0]))))
        assert np.abs(counts - change.reshape(-1) / C).max() <= 1.0


def test_linear_log_ramp_gives_exact_times() -> None:
    rate_per_us = C / 1000.0  # one threshold every 1000 µs

    def ramp(t_us: np.ndarray) -> np.ndarray:
        return np.exp(rate_per_us * np.asarray(t_us, dtype=np.float64))[:, None, None] * np.ones((1, 2, 3)) - LOG_EPS

    events = EventArray.concatenate(list(simulate_events(ramp, 0, 10_000, width=3, height=2)))
    assert np.array_equal(events.t, np.repeat(np.arange(1000, 10_001, 1000), 6))
    assert np.array_equal(events.x, np.tile([0, 1, 2, 0, 1, 2], 10))
    assert np.all(events.p == 1)
    dead = EventArray.concatenate(list(simulate_events(ramp, 0, 10_000, width=3, height=2, sensor=EventSensor(refractory_us=300))))
    # Reset at the end of the dead time: each event needs R + C/slope = 1300 µs.
    assert np.array_equal(np.unique(dead.t), np.arange(1000, 10_001, 1300))
    falling = EventArray.concatenate(list(simulate_events(lambda t: ramp(-np.asarray(t)), 0, 10_000, width=3, height=2)))
    assert np.array_equal(np.unique(falling.t), np.arange(1000, 10_001, 1000)) and np.all(falling.p == -1)


def test_sorted_typed_chunked_and_deterministic() -> None:
    render, *_ = sine_scene()
    events, chunks = run(render, 0, PERIOD_US, sigma=0.03, chunk_samples=16, seed=3)
    assert len(chunks) > 2
    for chunk in chunks:
        assert chunk.is_sorted() and len(chunk) > 0
    for before, after in zip(chunks, chunks[1:]):
        assert after.t[0] >= before.t[-1]
    assert events.x.dtype == np.uint16 and events.y.dtype == np.uint16
    assert events.t.dtype == np.int64 and events.p.dtype == np.int8
    assert set(np.unique(events.p)) == {-1, 1}
    assert events.t.min() >= 0 and events.t.max() <= PERIOD_US
    pixel = events.y.astype(np.int64) * SIZE + events.x
    same_time = events.t[1:] == events.t[:-1]
    assert np.all(pixel[1:][same_time] >= pixel[:-1][same_time])
    again, _ = run(render, 0, PERIOD_US, sigma=0.03, chunk_samples=16, seed=3)
    other, _ = run(render, 0, PERIOD_US, sigma=0.03, chunk_samples=16, seed=4)
    for c in "xytp":
        # bit-equal: the same seed runs the same code on the same machine
        assert np.array_equal(getattr(events, c), getattr(again, c))
    assert len(other) != len(events) or not np.array_equal(other.t, events.t)


def test_refractory_dead_time_and_reference_reset() -> None:
    render, *_ = sine_scene()
    refractory = 30_000.0
    events, _ = run(render, 0, PERIOD_US, refractory_us=refractory)
    free, _ = run(render, 0, PERIOD_US)
    assert 0 < len(events) < len(free)
    pairs = consecutive_pairs(events, SIZE)
    assert (pairs.t_us - pairs.t_prev_us).min() >= refractory
    residual = threshold_residuals(render, events, 0, refractory)
    assert np.abs(residual).max() < 2e-3


def test_render_is_called_with_bounded_batches() -> None:
    render, *_ = sine_scene()
    batches: list[int] = []

    def counted(t_us: np.ndarray) -> np.ndarray:
        batches.append(len(t_us))
        return render(t_us)

    events, _ = run(counted, 0, PERIOD_US, chunk_samples=8, initial_dt_us=50_000)
    assert max(batches) <= 8 and sum(batches) > 60
    assert np.abs(threshold_residuals(render, events, 0, 0.0)).max() < 2e-3


def test_shot_noise_rate() -> None:
    def constant(t_us: np.ndarray) -> np.ndarray:
        return np.full((len(t_us), SIZE, SIZE), 0.5)

    rate_hz, duration_us = 50.0, 1_000_000
    events, _ = run(constant, 0, duration_us, shot_noise_hz=rate_hz, seed=1)
    # at irradiance 0.5 the dark rate falls halfway to SHOT_NOISE_BRIGHT_FACTOR of it
    expected = rate_hz * (1 - 0.5 * (1 - SHOT_NOISE_BRIGHT_FACTOR)) * SIZE * SIZE * duration_us * 1e-6
    assert abs(len(events) - expected) < 4 * np.sqrt(expected)
    assert abs(np.sum(events.p == 1) - expected / 2) < 4 * np.sqrt(expected / 4)
    assert len(EventArray.concatenate(list(simulate_events(constant, 0, duration_us, width=SIZE, height=SIZE)))) == 0


def test_leak_fires_positive_events_at_the_leak_rate() -> None:
    def constant(t_us: np.ndarray) -> np.ndarray:
        return np.full((len(t_us), SIZE, SIZE), 0.5)

    events, _ = run(constant, 0, 2_000_000, leak_hz=5.0, seed=2)
    assert np.all(events.p == 1)
    counts = np.bincount(events.y.astype(np.int64) * SIZE + events.x, minlength=SIZE * SIZE)
    assert np.all(counts == 10)
    gaps = consecutive_pairs(events, SIZE)
    assert np.abs((gaps.t_us - gaps.t_prev_us) - 200_000).max() <= 1
    assert np.unique(events.t[::10]).size > 1  # pixels do not fire in lockstep


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"sensor": EventSensor(contrast_pos=-0.1)}, "simulate_events: contrast_pos must be a positive number, got -0.1"),
        ({"sensor": EventSensor(sigma=-1.0)}, "simulate_events: sigma must be zero or positive, got -1.0"),
        ({"sensor": EventSensor(refractory_rule="x")},
         "simulate_events: refractory rule 'x' is not one of reset-at-end, rate-limited"),
        ({"max_dlog": 0.0}, "simulate_events: max_dlog must be a positive number, got 0.0"),
        ({"chunk_samples": 1}, "simulate_events: chunk_samples must be at least 2, got 1"),
        ({"width": 0}, "simulate_events: sensor size 0x16 must be 1 to 65536 pixels per side"),
    ],
)
def test_bad_options(kwargs: dict, message: str) -> None:
    render, *_ = sine_scene()
    args = {"width": SIZE, "height": SIZE, **kwargs}
    with pytest.raises(UserError) as info:
        next(simulate_events(render, 0, PERIOD_US, **args))
    assert str(info.value) == message


def test_bad_render_output() -> None:
    with pytest.raises(UserError, match=r"render returned shape \(1, 4, 4\), expected \(1, 16, 16\)"):
        next(simulate_events(lambda t: np.ones((len(t), 4, 4)), 0, 1000, width=SIZE, height=SIZE))
    with pytest.raises(UserError, match="render returned negative or non-finite irradiance"):
        next(simulate_events(lambda t: -np.ones((len(t), SIZE, SIZE)), 0, 1000, width=SIZE, height=SIZE))


def test_a_step_in_irradiance_fires_every_crossing_at_the_step() -> None:
    """A jump between two samples (a hard shadow edge) is refined down to min_dt and its crossings all
    land at the step, without the sampler ever asking for an empty render."""
    def render(t_us: np.ndarray) -> np.ndarray:
        level = np.where(np.asarray(t_us, dtype=np.float64) > 5000.0, 2.0, 0.1)
        return level[:, None, None] * np.ones((1, 8, 8))

    events = EventArray.concatenate(list(simulate_events(render, 0, 10_000, width=8, height=8)))
    expected = int(np.floor((np.log(2.0 + LOG_EPS) - np.log(0.1 + LOG_EPS)) / 0.15))
    assert len(events) == 64 * expected
    assert np.all(events.p == 1)
    assert events.t.min() >= 4999 and events.t.max() <= 5001
