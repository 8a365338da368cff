"""DualResPS preprocessing: the interval profile, Algorithm 1 on hand-built event streams with known
shadows, the shadow lookup, importance sampling, the closed-form init on simulated captures, and
the contract the neural inverse rendering relies on."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pstoolkit_dualres.irradiance import approximate
from pstoolkit_dualres.preprocess import (
    Preprocessed,
    PreprocessOptions,
    preprocess,
    shadow_detector,
)
from pstoolkit_dualres.profile import interval_profile
from pstoolkit_dualres.sampling import Samples, importance_samples, segment_counts
from pstoolkit_dualres.shadows import (
    ShadowIntervals,
    ShadowTable,
    find_shadows,
    find_silences,
)

import psfmt
from pstoolkit.errors import UserError
from pstoolkit.eventmodel import consecutive_pairs
from pstoolkit.render import cast_shadow_mask
from pstoolkit.simulator import SimulationConfig, simulate

T = 33_333.0
C = 0.15
BURST_US = 10  # spacing of the events of a sharp shadow edge: one profile sample
THETA = {"theta": 4000.0, "theta_min": 500.0, "gamma": 0.7, "max_duration_us": T / 2}


def _stream(rows: list[list[tuple[float, int]]]) -> psfmt.EventArray:
    """Events of pixels 0, 1, … (one row of the sensor) from (t_us, polarity) lists, sorted by time."""
    x = np.concatenate([np.full(len(r), i) for i, r in enumerate(rows)])
    t = np.concatenate([[e[0] for e in r] for r in rows]).astype(np.int64)
    p = np.concatenate([[e[1] for e in r] for r in rows])
    order = np.argsort(t, kind="stable")
    return psfmt.EventArray(x[order], np.zeros(len(t)), t[order], p[order])


def _shading(t0: float, t1: float, step: float, polarity: int) -> list[tuple[float, int]]:
    """Slow shading events every ``step`` µs in [t0, t1): |f| = C/step, far below θ."""
    return [(t, polarity) for t in np.arange(t0, t1, step)]


def _burst(t0: float, n: int, spacing: float, polarity: int) -> list[tuple[float, int]]:
    return [(t0 + i * spacing, polarity) for i in range(n)]


def _shadowed(entry: float, exit_: float, entry_spacing: float = BURST_US) -> list[tuple[float, int]]:
    """A pixel dimming slowly, entering a shadow at ``entry`` (a burst of negative events, spaced
    ``entry_spacing``) and leaving it at ``exit_`` (the last event of a sharp positive burst)."""
    entry_burst = _burst(entry, 12, entry_spacing, -1)
    exit_burst = _burst(exit_ - 11 * BURST_US, 12, BURST_US, +1)
    before = _shading(0.0, entry - 2000.0, 2000.0, -1) if entry > exit_ else []
    return sorted(_shading(exit_ + 2000.0, entry - 1000.0, 2000.0, -1) + before + entry_burst + exit_burst)


def _cyclic_distance(a: np.ndarray, b: float) -> np.ndarray:
    d = np.mod(np.asarray(a) - b, T)
    return np.minimum(d, T - d)


@pytest.fixture(scope="module")
def stream() -> psfmt.EventArray:
    return _stream(
        [
            _shadowed(10_000.0, 16_000.0),  # sharp entry and exit
            _shadowed(10_000.0, 16_000.0, entry_spacing=250.0),  # entry softened: |f| = 600 < θ
            sorted(_burst(T - 3000.0, 12, BURST_US, -1) + _burst(2000.0 - 110, 12, BURST_US, +1) + _shading(6000.0, 25_000.0, 2500.0, -1)),
            sorted(_shading(500.0, 16_000.0, 1500.0, +1) + _shading(17_000.0, 33_000.0, 1500.0, -1)),  # no shadow
        ]
    )


def test_profile_is_eq20_with_cyclic_gap() -> None:
    events = _stream([[(1000.0, 1), (4000.0, -1), (4100.0, -1)], [(5000.0, 1)]])
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


def test_silences_stand_in_for_spikes_under_a_long_refractory_period() -> None:
    r = 2000.0
    # one event per edge: a dimming train, the entry swallowed by the refractory period, silence
    # until the exit at 20 000, then a brightening train; pixel 1 turns round smoothly instead
    shadowed = _shading(2000.0, 12_000.0, 2100.0, -1) + _shading(20_000.0, 31_000.0, 2100.0, +1)
    minimum = _shading(2000.0, 12_000.0, 2100.0, -1) + [(14_500.0, -1), (18_000.0, +1)] + _shading(20_500.0, 31_000.0, 2100.0, +1)
    profile = interval_profile(_stream([shadowed, minimum]), 2, t0_us=0.0, period_us=T, contrast_pos=C, contrast_neg=C)
    assert np.abs(profile.f).max() < 4000.0  # no spike for Algorithm 1
    found = find_silences(profile, ratio=3.0, refractory_us=r, max_duration_us=T / 2)
    assert found.pixel.tolist() == [0]
    np.testing.assert_allclose([found.t0_us[0], found.t1_us[0]], [10_400.0 + r / 2, 20_000.0])


def test_detector_follows_the_refractory_cap() -> None:
    options = PreprocessOptions()
    assert shadow_detector(options, C, 0.0) == ("spikes", 4000.0, 500.0)
    kind, theta, theta_min = shadow_detector(options, C, 100.0)  # |f| ≤ C/R = 1500/s
    assert kind == "spikes" and theta == pytest.approx(1000.0) and theta_min == 500.0
    assert shadow_detector(options, C, 2000.0)[0] == "off"
    assert shadow_detector(PreprocessOptions(silence_ratio=3.0), C, 2000.0)[0] == "silences"
    assert shadow_detector(PreprocessOptions(use_shadows=False), C, 0.0)[0] == "off"


def test_shadow_table_merges_and_wraps() -> None:
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


def test_importance_sampling_crowds_where_irradiance_changes_fast() -> None:
    # a fast rise in the first window (20 events 100 µs apart), the same fall slowly over the others
    fast = _shading(1000.0, 3000.0, 100.0, +1)
    slow = _shading(12_000.0, 12_000.0 + 20 * 1050.0, 1050.0, -1)
    events = _stream([fast + slow])
    profile = interval_profile(events, 1, t0_us=0.0, period_us=T, contrast_pos=C, contrast_neg=C)
    bounds = np.array([0.0, T / 3, 2 * T / 3, T])
    irradiance = approximate(
        profile.pixel, profile.t_us, profile.p, profile.first, profile.count, n_pixels=1, period_us=T,
        contrast_pos=C, contrast_neg=C, refractory_us=0.0, bounds_us=bounds,
        frame_values=np.array([[0.5, 0.5, 0.5]]), shadows=None,
    )
    samples = importance_samples(irradiance, profile.pixel, profile.t_us, n_pixels=1, sigma=40.0, max_step_us=T)
    def density(s: Samples, t0: float, t1: float) -> float:
        return float(np.sum((s.phase_us >= t0) & (s.phase_us < t1))) / (t1 - t0)

    assert density(samples, 1000.0, 3000.0) > 2.5 * density(samples, 12_000.0, 33_000.0)  # measured 3.1×
    # σ adds samples where Î changes most
    denser = importance_samples(irradiance, profile.pixel, profile.t_us, n_pixels=1, sigma=400.0, max_step_us=T)
    gain_fast = density(denser, 1000.0, 3000.0) - density(samples, 1000.0, 3000.0)
    gain_slow = density(denser, 12_000.0, 33_000.0) - density(samples, 12_000.0, 33_000.0)
    assert gain_fast > 1.5 * gain_slow > 0  # measured 1.9×
    np.testing.assert_array_equal(segment_counts(np.array([0.0, 1.0, 100.0]), np.array([1.0, 0.01, 0.01]), 40.0), [0, 3, 39])
    # the weights tile each window exactly, and reproduce its frame value from Î
    np.testing.assert_allclose(np.bincount(samples.window, weights=samples.dt_s), [T / 3e6] * 3, rtol=1e-9)
    integral = np.bincount(samples.window, weights=irradiance.value(samples.pixel, samples.phase_us) * samples.dt_s)
    np.testing.assert_allclose(integral, 0.5, rtol=0.05)


@pytest.fixture(scope="module")
def sphere_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A Lambertian sphere without cast shadows; no refractory, so edges fire bursts."""
    path = tmp_path_factory.mktemp("dualres") / "sphere.h5"
    simulate(SimulationConfig(scene="sphere", size=64, brdf="lambertian", shadows=False, refractory_us=0.0), path)
    return path


@pytest.fixture(scope="module")
def sphere(sphere_path: Path) -> tuple[psfmt.Capture, Preprocessed]:
    capture = psfmt.read(sphere_path)
    return capture, preprocess(capture, PreprocessOptions())


def _mae(normal: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> float:
    cosine = np.clip(np.sum(normal * truth, axis=-1), -1.0, 1.0)
    return float(np.degrees(np.arccos(cosine))[mask].mean())


def test_no_false_shadows_on_a_lambertian_sphere(sphere: tuple[psfmt.Capture, Preprocessed]) -> None:
    capture, pre = sphere
    gt = capture.ground_truth
    t = pre.t0_us + np.arange(0.0, T, T / 360)
    direction, _ = pre.light.evaluate(t)
    n_dot_l = direction @ gt.normal.reshape(-1, 3).T
    pixels = np.flatnonzero(gt.mask.ravel())
    detected = pre.in_shadow(np.tile(pixels, len(t)), np.repeat(t, len(pixels))).reshape(len(t), -1)
    lit = n_dot_l[:, pixels] > 0.1
    # what Algorithm 1 finds on a sphere is its attached shadow (the mixed shadow of the paper), never lit time
    assert detected.any()
    assert not (detected & lit).any()


def test_init_recovers_sphere_normals(sphere_path: Path, sphere: tuple[psfmt.Capture, Preprocessed]) -> None:
    capture, pre = sphere
    gt = capture.ground_truth
    mask = gt.mask & pre.mask
    assert _mae(pre.init_normal, gt.normal, mask) < 0.9  # measured 0.66° (8-bit frames)
    plain = preprocess(psfmt.read(sphere_path), PreprocessOptions(use_shadows=False))
    assert _mae(plain.init_normal, gt.normal, mask) < 0.8  # measured 0.57°
    # one step from the clamp of n = (0, 0, 1) is not enough near the terminator
    one = preprocess(psfmt.read(sphere_path), PreprocessOptions(use_shadows=False, init_iterations=1))
    assert _mae(one.init_normal, gt.normal, mask) > 2 * _mae(plain.init_normal, gt.normal, mask)
    # Table 1: pixels with fewer than three effective lights take their free direction from the
    # super pixels' event normals (11.9° when it came from frame pixels with three lights alone)
    fewer = mask & (pre.effective_lights < 3)
    assert fewer.sum() > 50
    assert _mae(pre.init_normal, gt.normal, fewer) < 4.0  # measured 2.13°
    np.testing.assert_allclose(np.linalg.norm(pre.init_normal[pre.mask], axis=-1), 1.0, atol=1e-5)
    assert np.all(pre.init_albedo[pre.mask] > 0)
    # the albedo is the true one times the exposure gain, the same for every pixel and channel
    three = mask & (pre.effective_lights == 3)
    ratio = pre.init_albedo[three] / gt.albedo[three]
    assert np.std(ratio) / np.mean(ratio) < 0.02


def test_preprocessed_contract(sphere: tuple[psfmt.Capture, Preprocessed]) -> None:
    capture, pre = sphere
    k, h, w = pre.frames.shape[:3]
    assert (k, h, w) == (3, 64, 64) and pre.frames.dtype == np.float32 and pre.saturated.shape == (k, h, w)
    assert (pre.event_height, pre.event_width) == (32, 32) and pre.effective_lights.shape == (h, w)
    # every masked frame pixel's samples of a frame tile its exposure window (less detected shadow)
    group = pre.frame_sample_pixel * k + pre.frame_sample_frame
    total = np.bincount(group, weights=pre.frame_sample_dt_s, minlength=h * w * k).reshape(h * w, k)
    window_s = (pre.t_end_us - pre.t_start_us) / 1e6
    lit = total[pre.mask.ravel() & ~np.isin(np.arange(h * w), np.flatnonzero(np.isin(pre.super_pixel, pre.shadow_pixel)))]
    np.testing.assert_allclose(lit, np.broadcast_to(window_s, lit.shape), rtol=1e-5)
    inside = (pre.frame_sample_t_us >= pre.t_start_us[pre.frame_sample_frame]) & (pre.frame_sample_t_us < pre.t_end_us[pre.frame_sample_frame])
    assert inside.all()
    assert not pre.in_shadow(pre.frame_sample_pixel, pre.frame_sample_t_us).any()
    # without a refractory period each event's reference is the pixel's previous event
    pairs = consecutive_pairs(capture.events.read(), pre.event_width)
    key = pairs.pixel * 2**40 + pairs.t_us
    slot = np.searchsorted(key, pre.event_pixel * 2**40 + pre.event_t_us)
    np.testing.assert_array_equal(pre.event_t_ref_us, pairs.t_prev_us[slot])
    # pairs touching a detected (here: attached) shadow are left out: 82 % remain
    assert np.all(pre.event_alpha == 1.0) and pre.event_pixel.size > 0.75 * pairs.pixel.size
    assert 0.0 <= pre.event_weight.min() and pre.event_weight.max() == 1.0 and pre.event_weight.min() < 0.5
    np.testing.assert_allclose(pre.event_frame_uv(np.array([0, 33])), [[0.5, 0.5], [2.5, 2.5]])


def test_frame_samples_integrate_the_true_irradiance(sphere: tuple[psfmt.Capture, Preprocessed]) -> None:
    """Σ I·dt over a (pixel, frame)'s samples, with the true Lambertian I = ρ·[n·l]₊, is the frame value
    up to the simulator's exposure gain, one number for every pixel and frame."""
    capture, pre = sphere
    gt = capture.ground_truth
    direction, _ = pre.light.evaluate(pre.frame_sample_t_us)
    normal = gt.normal.reshape(-1, 3)[pre.frame_sample_pixel]
    grey_albedo = gt.albedo.reshape(-1, 3)[pre.frame_sample_pixel] @ np.array([0.299, 0.587, 0.114])
    shading = grey_albedo * np.clip(np.sum(direction * normal, axis=1), 0.0, None)
    k = pre.frames.shape[0]
    group = pre.frame_sample_pixel * k + pre.frame_sample_frame
    integral = np.bincount(group, weights=shading * pre.frame_sample_dt_s, minlength=pre.height * pre.width * k)
    measured = (pre.frames @ np.array([0.299, 0.587, 0.114], dtype=np.float32)).reshape(k, -1).T.ravel()
    bright = measured > 0.2  # 8-bit quantisation stays below 1 %
    gain = measured[bright] / integral[bright]
    assert np.std(gain) / np.mean(gain) < 0.01  # measured 0.2 % with about 30 samples per pixel and frame


def test_refractory_rules_and_ablation(tmp_path: Path) -> None:
    path = tmp_path / "sphere_refractory.h5"
    simulate(SimulationConfig(scene="sphere", size=32, brdf="lambertian", shadows=False, refractory_us=2000.0), path)
    capture = psfmt.read(path)
    # R = 2 ms caps |f| at 75/s: no spikes, so no mask unless silences are asked for
    assert preprocess(capture, PreprocessOptions()).diagnostics["shadow_detector"] == "off"
    silences = preprocess(capture, PreprocessOptions(silence_ratio=3.0))
    assert silences.diagnostics["shadow_detector"] == "silences" and silences.shadow_pixel.size > 0
    reset = preprocess(capture, PreprocessOptions(use_shadows=False, confidence="none"))
    rate = preprocess(capture, PreprocessOptions(use_shadows=False, alpha_rule="rate"))
    assert reset.shadow_pixel.size == 0 and not reset.in_shadow(np.arange(10), np.zeros(10)).any()
    np.testing.assert_array_equal(reset.event_weight, 1.0)
    # "reset": the reference is taken when the refractory period ends, α = 1
    np.testing.assert_array_equal(reset.event_t_ref_us - rate.event_t_ref_us, 2000.0)
    np.testing.assert_array_equal(reset.event_alpha, 1.0)
    # "rate": the reference is the previous event and α credits the change missed meanwhile (≤ C)
    log_alpha = np.log(rate.event_alpha)
    assert np.all(log_alpha * rate.event_polarity > 0) and np.abs(log_alpha).max() <= C + 1e-12
    interval = rate.event_t_us - rate.event_t_ref_us
    expected = rate.event_polarity * C * 2000.0 / np.maximum(interval - 2000.0, 2000.0)
    np.testing.assert_allclose(log_alpha, expected, rtol=1e-12)


def test_blobs_shadows_match_the_simulated_cast_shadows(tmp_path: Path) -> None:
    path = tmp_path / "blobs.h5"
    simulate(SimulationConfig(scene="blobs", size=48, brdf="lambertian", refractory_us=0.0), path)
    capture = psfmt.read(path)
    pre = preprocess(capture, PreprocessOptions())
    gt = capture.ground_truth
    t = pre.t0_us + np.arange(0.0, T, T / 360)
    direction, _ = pre.light.evaluate(t)
    truth = cast_shadow_mask(gt.depth, gt.mask, direction).reshape(len(t), -1)
    n = pre.height * pre.width
    detected = pre.in_shadow(np.tile(np.arange(n), len(t)), np.repeat(t, n)).reshape(len(t), n)
    hit = np.sum(detected & truth)
    assert hit / detected.sum() > 0.7 and hit / truth.sum() > 0.8  # measured 0.80 and 0.86
    plain = preprocess(capture, PreprocessOptions(use_shadows=False))
    assert _mae(pre.init_normal, gt.normal, gt.mask) < 0.7 * _mae(plain.init_normal, gt.normal, gt.mask)  # 0.43° vs 0.97°


def test_bad_input_is_a_user_error(sphere_path: Path, tmp_path: Path) -> None:
    with pytest.raises(UserError, match=r"^dualres: option gamma = 1\.5 must be in \(0, 1\)$"):
        preprocess(psfmt.read(sphere_path), PreprocessOptions(gamma=1.5))
    frames_only = tmp_path / "frames.h5"
    simulate(SimulationConfig(scene="sphere", size=16, discrete_lights=4), frames_only)
    with pytest.raises(UserError, match=r"frames\.h5 is a frames capture; DualResPS needs frames and events$"):
        preprocess(psfmt.read(frames_only), PreprocessOptions())
