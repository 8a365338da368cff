"""DualResPS preprocessing: importance sampling, the event pairs of each refractory rule, the
closed-form init on simulated captures (with and without a cast-shadow mask), and the contract the
inverse rendering relies on. (Shadow detection is tested in test_shadows.py.)"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from helpers.event_rows import event_stream, shading

import psfmt
from pstoolkit import LightModel
from pstoolkit.errors import UserError
from pstoolkit.events.rule import consecutive_pairs
from pstoolkit.shadows import interval_profile
from pstoolkit.shadows.score import true_shadows
from pstoolkit.sim.config import SimulationConfig
from pstoolkit.sim.simulator import simulate
from pstoolkit_dualres.irradiance import approximate
from pstoolkit_dualres.preprocess import Preprocessed, PreprocessOptions, preprocess
from pstoolkit_dualres.sampling import Samples, importance_samples, segment_counts

T = 33_333.0
C = 0.15


def test_importance_sampling_crowds_where_irradiance_changes_fast() -> None:
    # a fast rise in the first window (20 events 100 µs apart), the same fall slowly over the others
    fast = shading(1000.0, 3000.0, 100.0, +1)
    slow = shading(12_000.0, 12_000.0 + 20 * 1050.0, 1050.0, -1)
    events = event_stream([fast + slow])
    profile = interval_profile(events, 1, t0_us=0.0, period_us=T, contrast_pos=C, contrast_neg=C)
    bounds = np.array([0.0, T / 3, 2 * T / 3, T])
    irradiance = approximate(
        profile.pixel, profile.t_us, profile.p, profile.first, profile.count, n_pixels=1, period_us=T,
        contrast_pos=C, contrast_neg=C, refractory_us=0.0, bounds_us=bounds,
        frame_values=np.array([[0.5, 0.5, 0.5]]),
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


def test_init_recovers_sphere_normals(sphere_path: Path, sphere: tuple[psfmt.Capture, Preprocessed]) -> None:
    capture, pre = sphere
    gt = capture.ground_truth
    mask = gt.mask & pre.mask
    init = pre.init
    assert _mae(init.normal, gt.normal, mask) < 0.8  # measured 0.57° (8-bit frames)
    # one step from the clamp of n = (0, 0, 1) is not enough near the terminator
    one = preprocess(psfmt.read(sphere_path), PreprocessOptions(init_iterations=1))
    assert _mae(one.init.normal, gt.normal, mask) > 2 * _mae(init.normal, gt.normal, mask)
    # Table 1: pixels with fewer than three effective lights take their free direction from the
    # super pixels' event normals (11.9° when it came from frame pixels with three lights alone)
    fewer = mask & (init.effective < 3)
    assert fewer.sum() > 50
    assert _mae(init.normal, gt.normal, fewer) < 4.0  # measured 2.1°
    np.testing.assert_allclose(np.linalg.norm(init.normal[pre.mask], axis=-1), 1.0, atol=1e-5)
    assert np.all(init.albedo[pre.mask] > 0)
    # the albedo is the true one times the exposure gain, the same for every pixel and channel (off
    # the grazing rim, whose 8-bit values are a few levels)
    three = mask & (init.effective == 3) & (gt.normal[..., 2] > 0.3)
    ratio = init.albedo[three] / gt.albedo[three]
    assert np.std(ratio) / np.mean(ratio) < 0.02


def test_preprocessed_contract(sphere: tuple[psfmt.Capture, Preprocessed]) -> None:
    capture, pre = sphere
    k, h, w = pre.frames.shape[:3]
    assert (k, h, w) == (3, 64, 64) and pre.frames.dtype == np.float32 and pre.saturated.shape == (k, h, w)
    assert (pre.event_height, pre.event_width) == (32, 32) and pre.init.effective.shape == (h, w)
    assert pre.per_window.shape == (3, h, w, 3) and pre.super_pixel.shape == (h * w,)
    # the importance samples of each super pixel tile each exposure window
    samples = pre.samples
    total = np.bincount(samples.pixel * 3 + samples.window, weights=samples.dt_s, minlength=32 * 32 * 3).reshape(-1, 3)
    window_s = np.diff(pre.windows_us, axis=1)[:, 0] / 1e6
    np.testing.assert_allclose(total, np.broadcast_to(window_s, total.shape), rtol=1e-5)
    # without a refractory period each event's reference is the pixel's previous event, one threshold away
    pairs = consecutive_pairs(capture.events.read(), pre.event_width)
    events = pre.events
    key = pairs.pixel * 2**40 + pairs.t_us
    slot = np.searchsorted(key, events.pixel * 2**40 + events.t_us.astype(np.int64))
    np.testing.assert_array_equal(events.t_ref_us, pairs.t_prev_us[slot])
    np.testing.assert_array_equal(events.target, np.where(pairs.p[slot] > 0, C, -C))
    assert events.pixel.size > 0.95 * pairs.pixel.size
    assert 0.0 <= events.weight.min() and events.weight.max() == 1.0 and events.weight.min() < 0.5
    # the evidence shadow detectors read covers the period's events at the super pixels
    evidence = pre.evidence
    assert evidence.frame_shape == (h, w) and evidence.event_shape == (32, 32) and evidence.normal is None
    assert len(evidence.profile) > 0 and evidence.profile.pixel.max() < 32 * 32


def true_level(gt: psfmt.GroundTruth, light: LightModel, t: np.ndarray, pixel: np.ndarray) -> np.ndarray:
    """ln of the true grey Lambertian irradiance of event pixel ``pixel`` (2×2 frame pixels of a
    32 px capture) at ``t``."""
    grey_albedo = gt.albedo @ np.array([0.299, 0.587, 0.114])
    shade = np.clip(np.einsum("hwc,tc->thw", gt.normal, light.evaluate(t)[0]), 0.0, None) * grey_albedo
    blocks = shade.reshape(len(t), 16, 2, 16, 2).mean(axis=(2, 4)).reshape(len(t), -1)
    return np.log(blocks[np.arange(len(t)), pixel] + 1e-3)


def test_event_pairs_follow_the_capture_refractory_rule(tmp_path: Path) -> None:
    """Each rule's pairs relate the true log irradiance of their super pixel exactly (up to the
    simulator's render steps)."""
    for rule in ("reset-at-end", "rate-limited"):
        path = tmp_path / f"{rule}.h5"
        simulate(SimulationConfig(scene="sphere", size=32, brdf="lambertian", shadows=False, refractory_us=1500.0,
                                  refractory_rule=rule), path)
        capture = psfmt.read(path)
        pre = preprocess(capture, PreprocessOptions(confidence="none"))
        assert pre.refractory_rule == rule and pre.diagnostics["refractory_rule"] == rule
        events = pre.events
        np.testing.assert_array_equal(events.weight, 1.0)
        gt = capture.ground_truth
        pick = np.arange(0, events.pixel.size, max(1, events.pixel.size // 300))
        change = (true_level(gt, pre.light, events.t_us[pick], events.pixel[pick])
                  - true_level(gt, pre.light, events.t_ref_us[pick], events.pixel[pick]))
        assert np.median(np.abs(change - events.target[pick])) < 0.01  # measured 0.0002 for both rules
        if rule == "rate-limited":
            assert np.any(np.abs(events.target) > C + 1e-9)  # pairs across events fired at the end of a blind time


def test_a_cast_shadow_mask_reaches_the_closed_form(tmp_path: Path) -> None:
    """The equivalent lights under the true mask give a better start on shadowed blobs than none."""
    path = tmp_path / "blobs.h5"
    simulate(SimulationConfig(scene="blobs", size=48, brdf="lambertian", refractory_us=0.0), path)
    capture = psfmt.read(path)
    pre = preprocess(capture, PreprocessOptions())
    gt = capture.ground_truth
    truth = true_shadows(gt.depth, gt.mask, pre.light, pre.t0_us, pre.period_us)
    masked = pre.closed_form(truth)
    assert _mae(masked.normal, gt.normal, gt.mask) < 0.6 * _mae(pre.init.normal, gt.normal, gt.mask)  # measured 0.43° vs 0.97°
    np.testing.assert_array_equal(pre.closed_form(None).normal, pre.init.normal)
    # solved only where the mask shadows, the others standing as in the unmasked start: the same start there
    shadowed = (truth.coverage() > 0).reshape(pre.mask.shape) & pre.mask
    assert 0 < shadowed.sum() < 0.5 * pre.mask.sum()
    only = pre.closed_form(truth, shadowed)
    np.testing.assert_allclose(only.normal[shadowed], masked.normal[shadowed], atol=1e-6)
    np.testing.assert_allclose(only.albedo[shadowed], masked.albedo[shadowed], atol=1e-6)
    np.testing.assert_array_equal(only.effective[shadowed], masked.effective[shadowed])
    assert not only.normal[~shadowed].any()


def test_bad_input_is_a_user_error(sphere_path: Path, tmp_path: Path) -> None:
    with pytest.raises(UserError, match=r"^dualres: option dark_level = 1\.5 must be in \[0, 1\)$"):
        preprocess(psfmt.read(sphere_path), PreprocessOptions(dark_level=1.5))
    frames_only = tmp_path / "frames.h5"
    simulate(SimulationConfig(scene="sphere", size=16, discrete_lights=4), frames_only)
    with pytest.raises(UserError, match=r"frames\.h5 is a frames capture; DualResPS needs frames and events$"):
        preprocess(psfmt.read(frames_only), PreprocessOptions())
