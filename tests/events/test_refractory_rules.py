"""The two refractory rules of ``pstoolkit.events.rule`` ("reset-at-end", "rate-limited") in both event
engines: against an event-by-event reference on random piecewise-linear log signals, on analytic
ramps, steps and a lag that outlives its change; the engines against each other on a scene;
``exact_pairs`` against the true log change; the rule through the simulator, the semi-real converter
and the capture's calibration."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from helpers.diligent import write_diligent

import psfmt
from psfmt import REFRACTORY_RULES, EventArray
from pstoolkit.cli import main
from pstoolkit.errors import UserError
from pstoolkit.events.rule import LOG_EPS, capture_rule, exact_pairs, log_irradiance
from pstoolkit.optics.brdf import GGX
from pstoolkit.optics.lights import RingLight
from pstoolkit.plugin.options import defaults
from pstoolkit.sim import ring_engine
from pstoolkit.sim.esim import simulate_events
from pstoolkit.sim.esim_pixels import PacedPixels
from pstoolkit.sim.exposure import exposure_samples
from pstoolkit.sim.render import Renderer
from pstoolkit.sim.ring_kernels import firing
from pstoolkit.sim.scenes import Blobs
from pstoolkit.sim.sensor import EventSensor
from pstoolkit.sim.simulator import SHADOW_STEP_DEG

C = 0.15
RESET, PACED = REFRACTORY_RULES


def reference_events(t: np.ndarray, level: np.ndarray, rule: str, r_us: float, c_pos: float = C, c_neg: float = C,
                     ) -> tuple[np.ndarray, np.ndarray]:
    """The events of one pixel seeing the piecewise-linear L through (``t``, ``level``), found one by
    one straight from the rule's words: the earliest time at which the pixel may fire and L is beyond
    a threshold; then the reference moves one threshold (rate-limited, or R = 0) or is reset to the
    level at the end of the blind time (reset-at-end). Times unrounded, µs."""
    times, signs = [], []
    ref, ready = float(level[0]), float(t[0])

    def at(x: float) -> float:
        return float(np.interp(x, t, level))

    while True:
        hi, lo = ref + c_pos, ref - c_neg
        event = None
        now = at(ready)
        if now >= hi or now <= lo:
            event = (ready, 1 if now >= hi else -1)
        else:
            for i in range(np.searchsorted(t, ready, side="right") - 1, len(t) - 1):
                a = max(float(t[i]), ready)
                la, lb = at(a), float(level[i + 1])
                for threshold, sign in ((hi, 1), (lo, -1)):
                    if (lb - threshold) * sign >= 0 and (la - threshold) * sign < 0:
                        event = (a + (threshold - la) / (lb - la) * (float(t[i + 1]) - a), sign)
                if event is not None:
                    break
        if event is None:
            break
        times.append(event[0])
        signs.append(event[1])
        if rule == PACED or r_us == 0:
            ref += event[1] * (c_pos if event[1] > 0 else c_neg)
            ready = event[0] + r_us
        else:
            ready = event[0] + r_us
            if ready > t[-1]:
                break
            ref = at(ready)
        if ready > t[-1]:
            break
    return np.array(times), np.array(signs, dtype=np.int8)


def random_signals(seed: int, count: int = 6, knots: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """(knots,) shared times (µs) and (count, knots) log levels: segments of 100–3000 µs changing L by
    up to ±1.2, and some jumps (1 µs, up to ±1.5), within ±2.97."""
    rng = np.random.default_rng(seed)
    span = rng.uniform(100.0, 3000.0, knots - 1)
    span[rng.random(knots - 1) < 0.2] = 1.0
    t = np.concatenate(([0.0], np.cumsum(np.round(span))))
    steps = rng.uniform(-1.2, 1.2, (count, knots - 1))
    steps[:, span == 1.0] = rng.uniform(-1.5, 1.5, (count, int((span == 1.0).sum())))
    # bounded away from the thresholds (multiples of C from 0), so the signal never rests on one
    level = np.clip(np.concatenate((np.zeros((count, 1)), np.cumsum(steps, axis=1)), axis=1), -2.97, 2.97)
    return t, level


def esim_events(t: np.ndarray, level: np.ndarray, rule: str, r_us: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """``pstoolkit.sim.esim`` on the signals, one pixel each, with samples at every knot (the log is
    linear between them, so the generator's lines are the signal's)."""

    def render(times: np.ndarray) -> np.ndarray:
        return np.exp(np.stack([np.interp(times, t, row) for row in level], axis=1))[:, None, :] - LOG_EPS

    events = EventArray.concatenate(list(simulate_events(
        render, float(t[0]), float(t[-1]), width=len(level), height=1,
        sensor=EventSensor(C, C, refractory_us=r_us, refractory_rule=rule), sample_times_us=t[1:-1], min_dt_us=0.5,
    )))
    return [(events.t[events.x == k], events.p[events.x == k]) for k in range(len(level))]


def kernel_events(t: np.ndarray, level: np.ndarray, rule: str, r_us: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """``pstoolkit.sim.ring_engine``'s firing and emission code on the signals, one lane each, stepped as
    its pixels step: lines changing L by at most C/2, jumps whole (as a step at ``min_dt_us``)."""
    lanes = len(level)
    times = [t[:1]]
    for i in range(len(t) - 1):
        change = np.abs(level[:, i + 1] - level[:, i]).max()
        pieces = 1 if t[i + 1] - t[i] <= 1.0 else max(1, int(np.ceil(change / (C / 2))))
        times.append(np.linspace(t[i], t[i + 1], pieces + 1)[1:])
    times = np.concatenate(times)
    levels = np.stack([np.interp(times, t, row) for row in level])
    paced = rule == PACED and r_us > 0
    hi, lo = levels[:, 0] + C, levels[:, 0] - C
    blind = np.full(lanes, -np.inf if paced else np.inf)
    c = np.full(lanes, C)
    fire = np.zeros((2 * firing.PACED_ROWS, lanes))
    out_t, out_p = np.zeros((lanes, 4096), np.int64), np.zeros((lanes, 4096), np.int8)
    n = np.zeros(lanes, np.int64)
    accepted = np.ones(lanes, np.bool_)
    for i in range(len(times) - 1):
        ta, tb = np.full(lanes, times[i]), np.full(lanes, times[i + 1])
        la, lb = levels[:, i].copy(), levels[:, i + 1].copy()
        if paced:
            firing.fire_lanes_paced(accepted, ta, la, tb, lb, c, c, r_us, hi, lo, blind, fire)
            for k in range(lanes):
                n[k] = firing.emit_paced(fire, k, r_us, out_t[k], out_p[k], n[k])
        else:
            firing.fire_lanes(accepted, ta, la, tb, lb, c, c, r_us, hi, lo, blind, fire)
            for k in range(lanes):
                n[k] = firing.emit(fire, k, times[i], times[i + 1], out_t[k], out_p[k], n[k])
    return [(out_t[k, : n[k]], out_p[k, : n[k]]) for k in range(lanes)]


ENGINES = {"esim": esim_events, "ring_engine": kernel_events}


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize(("rule", "r_us"), [(RESET, 0.0), (RESET, 700.0), (RESET, 2000.0), (PACED, 700.0), (PACED, 2000.0)])
def test_engines_follow_the_rule_on_random_piecewise_linear_signals(engine: str, rule: str, r_us: float) -> None:
    """Every event, its polarity and (to the µs the times are rounded to) its time, as the rule's
    words give them event by event, on signals with slow and fast lines and jumps."""
    total = 0
    for seed in range(3):
        t, level = random_signals(seed)
        for k, (times, signs) in enumerate(ENGINES[engine](t, level, rule, r_us)):
            expected_t, expected_p = reference_events(t, level[k], rule, r_us)
            assert len(times) == len(expected_t), (seed, k)
            np.testing.assert_array_equal(signs, expected_p, err_msg=f"{seed} {k}")
            assert np.abs(times - np.floor(expected_t + 0.5)).max(initial=0) <= 1, (seed, k)
            total += len(times)
    assert total > (300 if r_us < 2000 else 150)


def ramp_then(t_knots: list[float], l_knots: list[float]) -> tuple[np.ndarray, np.ndarray]:
    return np.array(t_knots), np.array([l_knots])


@pytest.mark.parametrize("engine", ENGINES)
def test_a_ramp_faster_than_c_over_r(engine: str) -> None:
    """L rises C per 1000 µs and R = 3000 µs: reset-at-end fires every R + C/s = 4000 µs; rate-limited
    every R, its reference falling behind by s·R − C = 0.3 an event."""
    t, level = ramp_then([0.0, 20_000.0], [0.0, 3.0])
    (reset_t, reset_p), = ENGINES[engine](t, level, RESET, 3000.0)
    np.testing.assert_array_equal(reset_t, [1000, 5000, 9000, 13000, 17000])
    (paced_t, paced_p), = ENGINES[engine](t, level, PACED, 3000.0)
    np.testing.assert_array_equal(paced_t, [1000, 4000, 7000, 10000, 13000, 16000, 19000])
    assert np.all(reset_p == 1) and np.all(paced_p == 1)
    lag = 0.15e-3 * paced_t - C * np.arange(1, 8)
    np.testing.assert_allclose(np.diff(lag), 0.3, atol=1e-9)


@pytest.mark.parametrize("engine", ENGINES)
def test_a_step(engine: str) -> None:
    """L steps up by 0.95 within 1 µs at 5000 µs and stays: reset-at-end fires once (the rest falls
    into the blind time and the reset takes the new level); rate-limited fires ⌊0.95/C⌋ = 6 times, R
    apart, until its reference has caught up within a threshold."""
    t, level = ramp_then([0.0, 5000.0, 5001.0, 30_000.0], [0.0, 0.0, 0.95, 0.95])
    (reset_t, _), = ENGINES[engine](t, level, RESET, 2000.0)
    np.testing.assert_array_equal(reset_t, [5000])
    (paced_t, paced_p), = ENGINES[engine](t, level, PACED, 2000.0)
    np.testing.assert_array_equal(paced_t, 5000 + 2000 * np.arange(6))
    assert np.all(paced_p == 1)


@pytest.mark.parametrize("engine", ENGINES)
def test_a_lag_outlives_its_change_and_fires_against_the_falling_level(engine: str) -> None:
    """L jumps up by 1 at 5000 µs, then falls 0.1 per 1000 µs; R = 2000 µs. The rate-limited pixel
    keeps firing positive events every R while the level stays above its rising threshold (0.8 ≥
    0.3 at 7000 µs, 0.6 ≥ 0.45 at 9000 µs, 0.4 < 0.6 at 11000 µs), then negative ones as the level
    falls through its thresholds: at 0.3 (12001 µs), then every R, as a threshold takes C/|s| =
    1500 µs < R."""
    t, level = ramp_then([0.0, 5000.0, 5001.0, 17_001.0], [0.0, 0.0, 1.0, -0.2])
    (paced_t, paced_p), = ENGINES[engine](t, level, PACED, 2000.0)
    np.testing.assert_array_equal(paced_t, [5000, 7000, 9000, 12001, 14001, 16001])
    np.testing.assert_array_equal(paced_p, [1, 1, 1, -1, -1, -1])


def test_one_line_can_hold_a_lag_run_and_a_run_of_its_own_sense() -> None:
    """A pixel with reference 0.15 and a positive lag, blind until 1000 µs, on a line falling from
    1.0 (999 µs) to −1.0 (1009 µs), R = 2 µs: at 1000 µs the level (0.8) is beyond 0.3, so it fires
    +1 once (then 0.4 < 0.45); the line crosses 0.15 at 1003.25 µs and fires −1 there and every R
    after (a threshold takes C/|s| = 0.75 µs < R) while it lasts: at 1005.25 and 1007.25 µs. Both
    engines' firing code, on the one line."""
    ta, la, tb, lb, r_us = 999.0, 1.0, 1009.0, -1.0, 2.0
    expected_t, expected_p = [1000, 1003, 1005, 1007], [1, -1, -1, -1]
    hi, lo, blind = np.array([0.3]), np.array([0.0]), np.array([1000.0])
    fire = np.zeros((2 * firing.PACED_ROWS, 1))
    c = np.array([C])
    firing.fire_lanes_paced(np.ones(1, np.bool_), np.array([ta]), np.array([la]), np.array([tb]), np.array([lb]),
                                c, c, r_us, hi, lo, blind, fire)
    out_t, out_p = np.zeros(8, np.int64), np.zeros(8, np.int8)
    n = firing.emit_paced(fire, 0, r_us, out_t, out_p, 0)
    np.testing.assert_array_equal(out_t[:n], expected_t)
    np.testing.assert_array_equal(out_p[:n], expected_p)
    np.testing.assert_allclose([hi[0], lo[0], blind[0]], [0.0, -0.3, 1009.25], atol=1e-12)
    pixels = PacedPixels(c.copy(), c.copy(), np.array([0.3]), np.array([0.0]), np.array([1000.0]), r_us)
    fired = pixels.fire(np.array([0]), ta, tb, np.array([la]), np.array([lb]))
    _, t, p = pixels._expand([fired], [0], np.array([ta, tb]))
    np.testing.assert_array_equal(np.floor(t + 0.5), expected_t)
    np.testing.assert_array_equal(p, expected_p)
    np.testing.assert_allclose([pixels.hi[0], pixels.lo[0], pixels.blind_until_us[0]], [0.0, -0.3, 1009.25], atol=1e-12)


def test_with_no_refractory_period_the_rules_are_one() -> None:
    t, level = random_signals(7)
    for engine in ENGINES.values():
        reset, paced = engine(t, level, RESET, 0.0), engine(t, level, PACED, 0.0)
        for (ta, pa), (tb, pb) in zip(reset, paced):
            np.testing.assert_array_equal(ta, tb)
            np.testing.assert_array_equal(pa, pb)


def test_exact_pairs_of_a_stream() -> None:
    """Pixel 1 fires at 0 (+), 2500 (+, a crossing), 4500 (+, R after: a bound), 6500 (−, a bound),
    9000 (−, a crossing); pixel 0 at 100 and 3000; R = 2000, C⁺ = 0.2, C⁻ = 0.1."""
    events = EventArray(x=np.array([1, 0, 1, 0, 1, 1, 1]), y=np.zeros(7, np.int64),
                        t=np.array([0, 100, 2500, 3000, 4500, 6500, 9000]), p=np.array([1, -1, 1, 1, 1, -1, -1]))
    reset = exact_pairs(events, 2, RESET, 2000.0, 0.2, 0.1)
    np.testing.assert_array_equal(reset.pixel, [0, 1, 1, 1, 1])
    np.testing.assert_array_equal(reset.t_ref_us, [2100, 2000, 4500, 6500, 8500])
    np.testing.assert_array_equal(reset.t_us, [3000, 2500, 4500, 6500, 9000])
    np.testing.assert_allclose(reset.delta_log, [0.2, 0.2, 0.2, -0.1, -0.1])
    paced = exact_pairs(events, 2, PACED, 2000.0, 0.2, 0.1, t_start_us=-5000.0)
    # exact: pixel 0 at 100 (first, long after the start) and 3000 (2900 later); pixel 1 at 0, 2500, 9000
    np.testing.assert_array_equal(paced.pixel, [0, 1, 1])
    np.testing.assert_array_equal(paced.t_ref_us, [100, 0, 2500])
    np.testing.assert_array_equal(paced.t_us, [3000, 2500, 9000])
    np.testing.assert_array_equal(paced.n_pos, [1, 1, 1])
    np.testing.assert_array_equal(paced.n_neg, [0, 0, 2])
    np.testing.assert_allclose(paced.delta_log, [0.2, 0.2, 0.0], atol=1e-15)
    # by default the stream starts at its first event: an event within R of it may follow an unseen one
    assert exact_pairs(events, 2, PACED, 2000.0, 0.2, 0.1).pixel.tolist() == [1]
    with pytest.raises(UserError, match="exact_pairs: refractory rule 'later' is not one of reset-at-end, rate-limited"):
        exact_pairs(events, 2, "later", 2000.0, 0.2, 0.1)


@pytest.mark.parametrize("rule", REFRACTORY_RULES)
def test_exact_pairs_carry_the_true_log_change_of_an_esim_stream(rule: str) -> None:
    rng = np.random.default_rng(1)
    phase, offset = rng.uniform(0, 2 * np.pi, (8, 8)), rng.uniform(1.2, 2.0, (8, 8))

    def render(t_us: np.ndarray) -> np.ndarray:
        return offset + np.sin(2 * np.pi * np.asarray(t_us, dtype=np.float64)[:, None, None] / 200_000.0 + phase)

    events = EventArray.concatenate(list(simulate_events(render, 0, 400_000, width=8, height=8,
                                                         sensor=EventSensor(refractory_us=5000.0, refractory_rule=rule))))
    pairs = exact_pairs(events, 8, rule, 5000.0, C, C, t_start_us=0.0)
    assert len(pairs.pixel) > (0.9 if rule == RESET else 0.2) * len(events)
    y, x = np.divmod(pairs.pixel, 8)

    def true(t_us: np.ndarray) -> np.ndarray:
        return log_irradiance(render(t_us))[np.arange(len(t_us)), y, x]

    residual = true(pairs.t_us.astype(np.float64)) - true(pairs.t_ref_us) - pairs.delta_log
    assert np.abs(residual).max() < 2e-3


PERIOD_US = 30000.0
MIN_DT_US = 20.0


@pytest.fixture(scope="module")
def blobs() -> Renderer:
    light = RingLight(elevation_deg=40.0, period_us=PERIOD_US, intensity=np.array([1.0, 0.9, 0.7]))
    maps = Blobs().build(48, 0, **defaults(Blobs.options))
    return Renderer(maps, light, GGX(), shadow_step_us=PERIOD_US / exposure_samples(light, 0, PERIOD_US, SHADOW_STEP_DEG))


def kernel_scene(r: Renderer, rule: str, r_us: float) -> EventArray:
    blocks = ring_engine.simulate_ring(r, event_scale=0.5, t1_us=PERIOD_US, window_ends_us=[PERIOD_US],
                                       sensor=EventSensor(C, C, refractory_us=r_us, refractory_rule=rule),
                                       min_dt_us=MIN_DT_US)
    return EventArray.concatenate([b.events for b in blocks])


@pytest.mark.parametrize("rule", REFRACTORY_RULES)
def test_the_engines_agree_on_a_scene(blobs: Renderer, rule: str) -> None:
    """Blobs under a ring light, R = 1.5 ms: the compiled engine and ``pstoolkit.sim.esim`` (whole-frame
    renders refined per pixel) give event counts within 1 % and within one event for most pixels."""
    events = kernel_scene(blobs, rule, 1500.0)
    reference = EventArray.concatenate(list(simulate_events(
        lambda t: blobs.event_grey(t, 0.5), 0, PERIOD_US, width=24, height=24,
        sensor=EventSensor(C, C, refractory_us=1500.0, refractory_rule=rule), min_dt_us=MIN_DT_US,
        render_pixels=lambda t, p: blobs.event_pixels(t, p, 0.5),
    )))
    assert len(reference) > 3000
    assert abs(len(events) - len(reference)) <= 0.01 * len(reference)
    counts = [np.bincount(e.y.astype(np.int64) * 24 + e.x, minlength=24 * 24) for e in (events, reference)]
    assert np.mean(np.abs(counts[0] - counts[1]) <= 1) > 0.95


def test_rate_limited_fires_more_and_its_exact_pairs_carry_the_rendered_log_change(blobs: Renderer) -> None:
    """The compiled engine's rate-limited stream of the scene: more events than reset-at-end (changes
    outlive the blind time); its exact pairs agree with the rendered log change within 2e-3 plus how
    far L moves within ``min_dt_us`` of either time (a cast shadow's edge is resolved to that step)."""
    events = kernel_scene(blobs, PACED, 1500.0)
    assert len(events) > 1.5 * len(kernel_scene(blobs, RESET, 1500.0))
    pairs = exact_pairs(events, 24, PACED, 1500.0, C, C, t_start_us=0.0)
    assert len(pairs.pixel) > 500
    y, x = np.divmod(pairs.pixel, 24)

    def true(t_us: np.ndarray) -> np.ndarray:
        return np.log(blobs.event_pixels(np.asarray(t_us, dtype=np.float64), pairs.pixel, 0.5) + LOG_EPS)

    def unresolved(t_us: np.ndarray) -> np.ndarray:
        return np.abs(true(t_us + MIN_DT_US) - true(t_us - MIN_DT_US))

    t, t_ref = pairs.t_us.astype(np.float64), pairs.t_ref_us
    residual = true(t) - true(t_ref) - pairs.delta_log
    assert np.all(np.abs(residual) < 2e-3 + unresolved(t) + unresolved(t_ref))
    assert np.median(np.abs(residual)) < 1e-3


def test_the_rule_is_an_option_of_the_simulator_and_recorded(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    counts = {}
    for rule in REFRACTORY_RULES:
        out = tmp_path / f"{rule}.h5"
        assert main(["simulate", "blobs", "-o", str(out), "--size", "32", "--period-ms", "10", "--refractory-us", "1000",
                     "--refractory-rule", rule, "-q"]) == 0
        assert psfmt.validate(out).valid
        with psfmt.read(out) as capture:
            assert capture.calibration.refractory_rule == rule and capture.calibration.refractory_us == 1000.0
            counts[rule] = len(capture.events)
        capsys.readouterr()
        assert main(["info", str(out)]) == 0
        assert f"  event sensor: contrast +0.15/−0.15, refractory 1000 µs, {rule}" in capsys.readouterr().out.splitlines()
    assert counts[PACED] > counts[RESET]
    assert main(["simulate", "blobs", "-o", str(tmp_path / "x.h5"), "--refractory-rule", "later", "-q"]) == 2
    assert capsys.readouterr().err == "pstoolkit: error: --refractory-rule 'later' must be reset-at-end or rate-limited\n"


def test_the_rule_is_an_option_of_the_semi_real_converter(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    folder = write_diligent(tmp_path / "ballPNG", height=40, width=48).folder
    counts = {}
    for rule in REFRACTORY_RULES:
        out = tmp_path / f"{rule}.h5"
        assert main(["convert", "diligent", str(folder), "--semi-real", "--size", "32", "--refractory-rule", rule,
                     "-o", str(out), "-q"]) == 0
        with psfmt.read(out) as capture:
            assert capture.calibration.refractory_rule == rule
            counts[rule] = len(capture.events)
    assert counts[PACED] > counts[RESET]
    capsys.readouterr()
    assert main(["convert", "diligent", str(folder), "--semi-real", "--refractory-rule", "later", "-o",
                 str(tmp_path / "x.h5")]) == 2
    assert "option refractory_rule: 'later' is not one of reset-at-end, rate-limited" in capsys.readouterr().err


def test_a_captures_rule_is_its_calibrations_or_the_formats_default() -> None:
    """``capture_rule``: the recorded rule, reset-at-end when none is recorded, one line naming the
    caller for a rule the toolkit does not know (a crafted file)."""
    assert capture_rule(psfmt.Calibration(refractory_rule="rate-limited"), "x") == "rate-limited"
    assert capture_rule(psfmt.Calibration(), "x") == REFRACTORY_RULES[0] == "reset-at-end"
    with pytest.raises(UserError, match=r"^eventps: c.h5: refractory rule 'reset-at-start' is not one of reset-at-end, rate-limited$"):
        capture_rule(psfmt.Calibration(refractory_rule="reset-at-start"), "eventps: c.h5")
