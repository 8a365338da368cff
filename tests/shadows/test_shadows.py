"""Cast-shadow detection (``pstoolkit.shadows``): the interval profile and Algorithm 1 on hand-built
event streams with known shadows, the dark spans of every refractory rule, the interval table, and
every registered detector's precision and recall per pixel-time against a simulated scene's truth."""

from __future__ import annotations

import numpy as np
import pytest
from helpers.event_rows import event_stream, shading

import psfmt
from pstoolkit.plugin.manager import get_registries
from pstoolkit.shadows import ShadowDetector, ShadowEvidence, ShadowIntervals, ShadowMask, ShadowTable, interval_profile
from pstoolkit.shadows.intervals import RunCollector, grid_times, intervals_from_grid, rasterize
from pstoolkit.shadows.score import score, true_shadows
from pstoolkit.shadows.silences import dark_spans
from pstoolkit.shadows.spikes import find_shadows, spike_threshold
from pstoolkit.sim.config import SimulationConfig
from pstoolkit.sim.simulator import simulate
from pstoolkit_dualres.preprocess import PreprocessOptions, preprocess

T = 33_333.0
C = 0.15
BURST_US = 10  # spacing of the events of a sharp shadow edge: one profile sample
THETA = {"theta": 4000.0, "theta_min": 500.0, "gamma": 0.7, "max_duration_us": T / 2}


def _burst(t0: float, n: int, spacing: float, polarity: int) -> list[tuple[float, int]]:
    return [(t0 + i * spacing, polarity) for i in range(n)]


def _shadowed(entry: float, exit_: float, entry_spacing: float = BURST_US) -> list[tuple[float, int]]:
    """A pixel dimming slowly, entering a shadow at ``entry`` (a burst of negative events, spaced
    ``entry_spacing``) and leaving it at ``exit_`` (the last event of a sharp positive burst)."""
    entry_burst = _burst(entry, 12, entry_spacing, -1)
    exit_burst = _burst(exit_ - 11 * BURST_US, 12, BURST_US, +1)
    before = shading(0.0, entry - 2000.0, 2000.0, -1) if entry > exit_ else []
    return sorted(shading(exit_ + 2000.0, entry - 1000.0, 2000.0, -1) + before + entry_burst + exit_burst)


def _profile(rows: list[list[tuple[float, int]]]):
    return interval_profile(event_stream(rows), len(rows), t0_us=0.0, period_us=T, contrast_pos=C, contrast_neg=C)


@pytest.fixture(scope="module")
def stream() -> psfmt.EventArray:
    return event_stream(
        [
            _shadowed(10_000.0, 16_000.0),  # sharp entry and exit
            _shadowed(10_000.0, 16_000.0, entry_spacing=250.0),  # entry softened: |f| = 600 < θ
            sorted(_burst(T - 3000.0, 12, BURST_US, -1) + _burst(2000.0 - 110, 12, BURST_US, +1) + shading(6000.0, 25_000.0, 2500.0, -1)),
            sorted(shading(500.0, 16_000.0, 1500.0, +1) + shading(17_000.0, 33_000.0, 1500.0, -1)),  # no shadow
        ]
    )


def test_profile_is_eq20_with_cyclic_gap() -> None:
    events = event_stream([[(1000.0, 1), (4000.0, -1), (4100.0, -1)], [(5000.0, 1)]])
    profile = interval_profile(events, 2, t0_us=0.0, period_us=T, contrast_pos=0.2, contrast_neg=0.1)
    assert profile.pixel.tolist() == [0, 0, 0, 1]
    expected = [0.2 / ((1000.0 + T - 4100.0) * 1e-6), -0.1 / 3000e-6, -0.1 / 100e-6, 0.2 / (T * 1e-6)]
    np.testing.assert_allclose(profile.f, expected, rtol=1e-12)


def test_algorithm1_finds_shadows_within_one_sample(stream: psfmt.EventArray) -> None:
    profile = interval_profile(stream, 4, t0_us=0.0, period_us=T, contrast_pos=C, contrast_neg=C)
    table = ShadowTable.build(find_shadows(profile, **THETA), T)
    found = {p: (table.start[i] - 2 * T * p, table.end[i] - 2 * T * p) for i, p in enumerate((table.start // (2 * T)).astype(int))}
    start, end = found[0]
    assert abs(start - 10_000.0) <= BURST_US and abs(end - 16_000.0) <= BURST_US
    # the softened entry is found by the decayed threshold, within one of its (wider) samples
    start, end = found[1]
    assert abs(start - 10_000.0) <= 250.0 and abs(end - 16_000.0) <= BURST_US
    # pixel 2's shadow wraps past the period's end: it is split into [T − 3000, T) and [0, 2000)
    assert table.contains(np.array([2, 2, 2, 2]), np.array([T - 2990.0, 100.0, 1990.0, 2020.0])).tolist() == [True, True, True, False]
    assert not table.contains(np.full(400, 3), np.linspace(0, T, 400)).any()
    coverage = table.coverage(4)
    np.testing.assert_allclose(coverage[[0, 2, 3]], [6000.0 / T, 5000.0 / T, 0.0], atol=2 * BURST_US / T)


def test_softened_edge_needs_threshold_decay(stream: psfmt.EventArray) -> None:
    profile = interval_profile(stream, 4, t0_us=0.0, period_us=T, contrast_pos=C, contrast_neg=C)
    no_decay = find_shadows(profile, **{**THETA, "theta_min": THETA["theta"]})
    assert 1 not in set(no_decay.pixel.tolist()) and 0 in set(no_decay.pixel.tolist())
    # a maximum duration shorter than a shadow with sharp edges rejects it
    short = find_shadows(profile, **{**THETA, "max_duration_us": 5000.0})
    assert 0 not in set(short.pixel.tolist()) and 0 in set(find_shadows(profile, **THETA).pixel.tolist())


def test_the_spike_threshold_follows_the_refractory_cap() -> None:
    assert spike_threshold(4000.0, C, 0.0) == 4000.0
    assert spike_threshold(4000.0, C, 100.0) == pytest.approx(1000.0)  # |f| ≤ C/R = 1500/s
    assert spike_threshold(4000.0, C, 2000.0) == pytest.approx(50.0)  # below the floor: no spikes at 2 ms


def test_dark_spans_of_each_refractory_rule() -> None:
    r = 2000.0
    # reset-at-end: the entry fires one negative event, silence until the exit's positive event
    reset = shading(2000.0, 12_000.0, 2100.0, -1) + shading(20_000.0, 31_000.0, 2100.0, +1)
    # rate-limited: negative events every R while in shadow from 12 000, then positive ones every R
    rate = shading(2000.0, 10_000.0, 2500.0, -1) + _burst(12_000.0, 4, r, -1) + _burst(20_000.0, 4, r, +1)
    # a smooth minimum: the events slow down gradually before turning
    minimum = shading(2000.0, 12_000.0, 2100.0, -1) + [(14_500.0, -1), (18_000.0, +1)] + shading(20_500.0, 31_000.0, 2100.0, +1)
    profile = _profile([reset, rate, minimum])
    found = dark_spans(profile, refractory_us=r, min_gap_us=r)
    spans = {int(p): (a, b) for p, a, b in zip(found.pixel, found.t0_us, found.t1_us)}
    assert spans[0] == (10_400.0, 20_000.0)
    assert spans[1] == (12_000.0, 20_000.0)  # the run's first event, not its last
    assert spans[2] == (14_500.0, 18_000.0)
    # the smooth minimum is only half as long as the intervals beside it: a ratio test rejects it
    strict = dark_spans(profile, refractory_us=r, min_gap_us=r, ratio=3.0)
    assert sorted(strict.pixel.tolist()) == [0, 1]


def test_shadow_table_merges_wraps_and_measures() -> None:
    shadows = ShadowIntervals(
        pixel=np.array([5, 5, 5, 0]),
        t0_us=np.array([100.0, 150.0, T - 50.0, 0.0]),
        t1_us=np.array([200.0, 300.0, 40.0, T - 1.0]),
    )
    table = ShadowTable.build(shadows, T)
    assert len(table) == 4  # pixel 0 almost all period; pixel 5: [100, 300] merged, the wrap split in two
    pixel = np.array([5, 5, 5, 5, 5, 5, 4, 0])
    t = np.array([99.0, 100.0, 300.0, 301.0, T + 20.0, T - 50.0, 150.0, T - 0.5])
    assert table.contains(pixel, t).tolist() == [False, True, True, False, True, True, False, False]
    np.testing.assert_allclose(table.coverage(6)[5], (200.0 + 90.0) / T)
    # time in shadow between two phases, across the period's end and for other pixels
    spent = table.shadowed_us(np.array([5, 5, 5, 4, 0]), np.array([0.0, 250.0, T - 100.0, 0.0, 10.0]),
                              np.array([T, 1000.0, T + 100.0, T, 20.0]))
    np.testing.assert_allclose(spent, [290.0, 50.0, 90.0, 0.0, 10.0])


def test_the_grid_lookups_answer_as_the_single_ones() -> None:
    """``contains_grid``/``shadowed_grid`` (a compiled scan of each pixel's rows) give what
    ``contains``/``shadowed_us`` give query by query, wrapping windows and unshadowed pixels too."""
    rng = np.random.default_rng(1)
    pixel = rng.integers(0, 300, 500)
    t0 = rng.uniform(0.0, T, pixel.size)
    table = ShadowTable.build(ShadowIntervals(pixel, t0, np.mod(t0 + rng.uniform(0.0, 0.6 * T, pixel.size), T)), T)
    query = np.arange(-5, 320)
    times = np.r_[rng.uniform(-2 * T, 3 * T, 30), 0.0, T]
    single = np.stack([table.contains(query, np.full(query.size, t)) for t in times])
    np.testing.assert_array_equal(table.contains_grid(query, times), single)
    start = rng.uniform(-2 * T, 2 * T, 30)
    stop = start + np.r_[rng.uniform(0.0, T, 28), 0.0, T]
    single = np.stack([table.shadowed_us(query, np.full(query.size, a), np.full(query.size, b)) for a, b in zip(start, stop)])
    np.testing.assert_allclose(table.shadowed_grid(query, start, stop), single, atol=1e-6)
    mask = ShadowMask(table, np.arange(400)[::-1].copy(), 1234.0)
    frame = np.arange(90, 120)
    np.testing.assert_array_equal(mask.contains_grid(frame, times), np.stack([mask.contains(frame, np.full(frame.size, t)) for t in times]))
    np.testing.assert_allclose(mask.shadowed_grid(frame, start, stop), np.stack(
        [mask.shadowed_us(frame, np.full(frame.size, a), np.full(frame.size, b)) for a, b in zip(start, stop)]), atol=1e-6)


def test_a_grid_of_shadows_becomes_intervals_and_back() -> None:
    rng = np.random.default_rng(0)
    grid = rng.random((72, 5)) < 0.3
    grid[:, 0] = False
    grid[:, 1] = True
    found = intervals_from_grid(grid, T, pixels=np.arange(5) + 10)
    assert 0 + 10 not in set(found.pixel.tolist())
    back = rasterize(found, 15, T, 72)[:, 10:]
    np.testing.assert_array_equal(back, grid)
    table = ShadowTable.build(found, T)
    np.testing.assert_array_equal(table.contains(np.repeat(np.arange(5) + 10, 72), np.tile(grid_times(T, 72), 5)).reshape(5, 72).T, grid)
    # intervals in any pixel order, wrapping ones among them: the bins whose centres they hold
    pixel = rng.integers(0, 50, 200)
    t0 = rng.uniform(0.0, T, pixel.size)
    intervals = ShadowIntervals(pixel, t0, np.mod(t0 + rng.uniform(0.0, 0.5 * T, pixel.size), T))
    assert np.any(intervals.t1_us < intervals.t0_us)
    np.testing.assert_array_equal(rasterize(intervals, 60, T, 72),
                                  ShadowTable.build(intervals, T).contains_grid(np.arange(60), grid_times(T, 72)))
    # more columns than one block of the compiled scan, runs at both ends of the period among them
    wide = rng.random((40, 1000)) < 0.5
    found = intervals_from_grid(wide, T)
    np.testing.assert_array_equal(rasterize(found, 1000, T, 40), wide)
    assert np.all(np.diff(found.pixel) >= 0)
    # fed a few rows at a time, runs carried across the blocks: the same intervals in the same order
    runs = RunCollector(1000)
    for lo, hi in ((0, 7), (7, 8), (8, 8), (8, 30), (30, 40)):
        runs.feed(wide[lo:hi])
    blocked = runs.intervals(T)
    for got, expected in zip((blocked.pixel, blocked.t0_us, blocked.t1_us), (found.pixel, found.t0_us, found.t1_us)):
        np.testing.assert_array_equal(got, expected)


def test_every_builtin_detector_is_registered_with_its_options() -> None:
    registry = get_registries().shadow_detectors
    assert registry.names() == ["fused", "geometry", "none", "silences", "spikes"]
    for name in registry.names():
        entry = registry.get(name)
        assert issubclass(entry.obj, ShadowDetector) and entry.plugin == "core" and entry.summary
    assert {o.name for o in registry.get("spikes").options} == {"theta_per_s", "theta_min_per_s", "gamma", "max_shadow_share"}
    assert registry.get("fused").obj.uses_surface and not registry.get("silences").obj.uses_surface


@pytest.fixture(scope="module")
def scenes(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[psfmt.Capture, ShadowEvidence, ShadowMask]]:
    """48 px GGX blobs (known shadow intervals from its depth) at 2 ms under each refractory rule and
    without a refractory period, with the evidence dualres builds and the true mask."""
    out = {}
    folder = tmp_path_factory.mktemp("shadows")
    for label, refractory, rule in (("reset", 2000.0, "reset-at-end"), ("rate", 2000.0, "rate-limited"), ("none", 0.0, "reset-at-end")):
        path = folder / f"{label}.h5"
        simulate(SimulationConfig(scene="blobs", size=48, seed=0, refractory_us=refractory, refractory_rule=rule), path)
        capture = psfmt.read(path)
        pre = preprocess(capture, PreprocessOptions())
        gt = capture.ground_truth
        out[label] = (capture, pre.evidence, true_shadows(gt.depth, gt.mask, pre.light, pre.t0_us, pre.period_us))
    return out


def _rate(scenes: dict, label: str, detector: str, *assignments: str, surface: bool = True) -> tuple[float, float]:
    capture, evidence, truth = scenes[label]
    entry = get_registries().shadow_detectors.get(detector)
    if surface:
        evidence = evidence.with_normal(capture.ground_truth.normal)
    return score(entry.obj().detect(evidence, entry.parse_options(list(assignments))), truth, capture.ground_truth.mask)


@pytest.mark.parametrize("label", ["reset", "rate", "none"])
def test_the_surface_detectors_on_the_true_surface(scenes: dict, label: str) -> None:
    """With the true normals the integrated surface predicts the shadows; the events confirm them."""
    precision, recall = _rate(scenes, label, "geometry")
    assert precision > 0.95 and recall > 0.9  # measured 1.00 / 0.98
    precision, recall = _rate(scenes, label, "fused")
    assert precision > 0.95 and recall > 0.7  # measured 1.00 / 0.87 (reset), 0.78 (rate), 0.79 (no R)
    # without a surface there is nothing to march: no mask
    assert _rate(scenes, label, "fused", surface=False)[1] == 0.0


def test_the_event_detectors_where_they_work(scenes: dict) -> None:
    # Algorithm 1 sees bursts only without a long refractory period
    precision, recall = _rate(scenes, "none", "spikes")
    assert precision > 0.7 and recall > 0.75  # measured 0.80 / 0.86
    assert _rate(scenes, "reset", "spikes") == (1.0, 0.0)
    # silences see shadows at 2 ms, at a lower precision
    precision, recall = _rate(scenes, "reset", "silences")
    assert precision > 0.6 and recall > 0.3  # measured 0.71 / 0.41
    assert _rate(scenes, "reset", "none") == (1.0, 0.0)


def test_a_detector_option_changes_its_mask(scenes: dict) -> None:
    loose = _rate(scenes, "reset", "geometry", "margin_px=-1.0")
    tight = _rate(scenes, "reset", "geometry")
    assert loose[1] >= tight[1] and loose[0] < tight[0]
