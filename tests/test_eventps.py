"""The eventps solver: exact on a hand-built event stream, accurate on a simulated Lambertian sphere
(events at half the frame resolution), one map per window, interval filtering and bad input."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import binary_dilation

import psfmt
from pstoolkit.errors import UserError
from pstoolkit.lights import SampledLight
from pstoolkit.metrics import angular_error_deg
from pstoolkit.plugins import get_registries
from pstoolkit.simulator import SimulationConfig, simulate
from pstoolkit.solver import SolverResult, run_solver

LUMA = np.array([0.299, 0.587, 0.114])
NORMAL = np.array([0.3, -0.2, 0.9]) / np.linalg.norm([0.3, -0.2, 0.9])
CONTRAST = 0.2
REFRACTORY_US = 500
EVENT_T_US = np.array([1000, 11000, 21000, 31000, 41000])
POLARITY = np.array([1, 1, -1, 1, -1])
PIXEL_XY = (2, 1)


def _solve(capture: psfmt.Capture, *assignments: str) -> SolverResult:
    entry = get_registries().solvers.get("eventps")
    result, _ = run_solver(entry, capture, entry.parse_options(list(assignments)))
    return result


def _unit_with_dot(rng: np.random.Generator, dot: float) -> np.ndarray:
    """A random unit vector d with NORMAL·d = dot."""
    u = np.cross(NORMAL, rng.normal(size=3))
    u /= np.linalg.norm(u)
    return dot * NORMAL + np.sqrt(1.0 - dot * dot) * u


def hand_built_capture() -> psfmt.Capture:
    """One pixel of a 3×2 sensor fires at EVENT_T_US under a sampled light whose samples sit exactly
    at each pair's reference time (t_prev + refractory) and event time, chosen so that
    NORMAL·l(t_k) = e^{p_k C}·NORMAL·l(t_prev + R) holds exactly, with l = direction × luma(intensity)."""
    rng = np.random.default_rng(3)
    times, directions, intensities = [], [], []
    for k in range(1, len(EVENT_T_US)):
        e_ref, e_now = rng.uniform(0.5, 1.5, 3), rng.uniform(0.5, 1.5, 3)
        dot_ref = rng.uniform(0.3, 0.5)
        dot_now = np.exp(POLARITY[k] * CONTRAST) * dot_ref * (e_ref @ LUMA) / (e_now @ LUMA)
        times += [EVENT_T_US[k - 1] + REFRACTORY_US, EVENT_T_US[k]]
        directions += [_unit_with_dot(rng, dot_ref), _unit_with_dot(rng, dot_now)]
        intensities += [e_ref, e_now]
    light = SampledLight(times_us=np.array(times, float), directions=np.array(directions), intensities=np.array(intensities))
    n = len(EVENT_T_US)
    events = psfmt.EventArray(x=np.full(n, PIXEL_XY[0]), y=np.full(n, PIXEL_XY[1]), t=EVENT_T_US, p=POLARITY)
    return psfmt.Capture(
        events=psfmt.Events(width=3, height=2, data=events),
        lights=light.to_spec(),
        calibration=psfmt.Calibration(contrast_pos=CONTRAST, contrast_neg=CONTRAST, refractory_us=REFRACTORY_US),
    )


def test_hand_built_stream_gives_the_exact_normal() -> None:
    result = _solve(hand_built_capture())
    expected_mask = np.zeros((2, 3), bool)
    expected_mask[PIXEL_XY[1], PIXEL_XY[0]] = True
    assert np.array_equal(result.mask, expected_mask)
    np.testing.assert_allclose(result.normal[PIXEL_XY[1], PIXEL_XY[0]], NORMAL, atol=1e-6)
    assert result.diagnostics["pairs"] == 4 and result.diagnostics["constraints"] == 4


def test_the_refractory_and_contrast_options_matter() -> None:
    """Evaluating the previous light at t_prev instead of t_prev + R, or with the wrong C, breaks it."""
    capture = hand_built_capture()
    y, x = PIXEL_XY[1], PIXEL_XY[0]
    for assignment in ("refractory_us=1", "contrast=0.3"):
        normal = _solve(capture, assignment).normal[y, x]
        assert np.degrees(np.arccos(np.clip(normal @ NORMAL, -1, 1))) > 1.0


def test_windows_split_the_pairs_by_the_later_event() -> None:
    """Windows of 20 ms: [0, 20) holds one pair (too few), [20, 40) two, [40, 60) one."""
    result = _solve(hand_built_capture(), "window_us=20000")
    sequence = result.maps["normal_sequence"]
    assert sequence.shape == (3, 2, 3, 3) and sequence.dtype == np.float32
    assert result.diagnostics["window_start_us"] == [0, 20000, 40000]
    y, x = PIXEL_XY[1], PIXEL_XY[0]
    assert not sequence[0].any() and not sequence[2].any()
    np.testing.assert_allclose(sequence[1, y, x], NORMAL, atol=1e-6)
    assert np.count_nonzero(np.linalg.norm(sequence[1], axis=-1)) == 1


def test_interval_filter() -> None:
    """Every pair is 10 ms apart: a 9 ms maximum drops them all, a 10 ms minimum keeps them."""
    capture = hand_built_capture()
    assert _solve(capture, "max_interval_us=9000").diagnostics["constraints"] == 0
    assert not _solve(capture, "max_interval_us=9000").mask.any()
    assert _solve(capture, "min_interval_us=10000").diagnostics["constraints"] == 4
    assert _solve(capture, "min_interval_us=10001").diagnostics["constraints"] == 0


@pytest.fixture(scope="module")
def sphere(tmp_path_factory: pytest.TempPathFactory) -> psfmt.Capture:
    """A Lambertian sphere, 64 px frames and 32 px events, two turns of the ring light. A sphere
    casts no shadow on itself, so the cast-shadow marcher is off: the test is about the solver."""
    path = tmp_path_factory.mktemp("eventps") / "sphere.h5"
    simulate(SimulationConfig(scene="sphere", size=64, brdf="lambertian", periods=2, shadows=False), path)
    return psfmt.load(path)


def _mae(normal: np.ndarray, capture: psfmt.Capture) -> float:
    """MAE over the ground-truth mask with pixels left out (zero normal) counted as 90°."""
    gt = capture.ground_truth
    return float(angular_error_deg(normal, gt.normal, gt.mask)[gt.mask].mean())


def test_simulated_sphere(sphere: psfmt.Capture) -> None:
    result = _solve(sphere)
    assert result.normal.shape == (64, 64, 3)
    normal = np.where(result.mask[..., None], result.normal, 0.0)
    # measured 4.45°: 0.9° on the 96 % of pixels with constraints; the rest (|n_xy| < 0.2, whose
    # log-irradiance barely changes round the ring) fire too few events and count as 90°
    assert _mae(normal, sphere) < 5.5
    covered = result.mask & sphere.ground_truth.mask
    assert covered.sum() > 0.94 * sphere.ground_truth.mask.sum()
    assert np.nanmean(angular_error_deg(result.normal, sphere.ground_truth.normal, covered)) < 1.5
    # the background fires nothing; only event pixels straddling the limb reach past it, by < 1 event pixel
    assert not (result.mask & ~binary_dilation(sphere.ground_truth.mask, iterations=2)).any()


def test_one_map_per_turn(sphere: psfmt.Capture) -> None:
    period = sphere.lights.params["period_us"]
    result = _solve(sphere, f"window_us={period}")
    sequence = result.maps["normal_sequence"]
    assert sequence.shape == (2, 64, 64, 3)
    assert result.diagnostics["window_start_us"] == [0, int(period)]
    for normal in sequence:
        assert _mae(normal, sphere) < 6.0  # measured 4.6° and 4.8°


def test_missing_calibration_is_one_clear_error() -> None:
    capture = hand_built_capture()
    capture.calibration = psfmt.Calibration()
    with pytest.raises(UserError, match=r"^eventps: the capture has no contrast threshold in its calibration; set one with --set contrast=C$"):
        _solve(capture)
    assert _solve(capture, f"contrast={CONTRAST}", f"refractory_us={REFRACTORY_US}").mask.sum() == 1


def test_closed_form_eigenvectors_match_lapack() -> None:
    from pstoolkit.eventnormals import symmetric_eigen

    rng = np.random.default_rng(3)
    v = rng.normal(size=(500, 6, 3))
    sums = np.einsum("bki,bkj->bij", v, v)
    values, vector = symmetric_eigen(sums)
    ref_values, ref_vectors = np.linalg.eigh(sums)
    np.testing.assert_allclose(values, ref_values, rtol=1e-9, atol=1e-9)
    cosine = np.abs(np.einsum("bi,bi->b", vector, ref_vectors[:, :, 0]))
    assert np.degrees(np.arccos(np.clip(cosine.min(), -1.0, 1.0))) < 1e-5
