"""The irradiance approximation of DualResPS (supplement eq. 1): the piecewise-constant scale s with
at most three values per period, changing at the ends of the strongest bursts of the interval
profile (the paper's rule) or at the exposure window bounds, fitted to the three frame values."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import psfmt
from pstoolkit.errors import UserError
from pstoolkit.shadows import interval_profile
from pstoolkit.sim.config import SimulationConfig
from pstoolkit.sim.simulator import simulate
from pstoolkit_dualres.irradiance import Irradiance, approximate
from pstoolkit_dualres.preprocess import PreprocessOptions, preprocess

T = 33_333.0
C = 0.15
BOUNDS = np.array([0.0, T / 3, 2 * T / 3, T])


def _pixel(events: list[tuple[float, int]]) -> psfmt.EventArray:
    t = np.array([e[0] for e in events], dtype=np.int64)
    p = np.array([e[1] for e in events])
    return psfmt.EventArray(np.zeros(len(t)), np.zeros(len(t)), t, p)


def _steps(t0: float, n: int, spacing: float, polarity: int) -> list[tuple[float, int]]:
    return [(t0 + i * spacing, polarity) for i in range(n)]


# slow shading (|f| = 150/s) and three sharp edges, bursts of events 10 µs apart (|f| = 15 000/s)
STREAM = _pixel(
    _steps(1000.0, 8, 1000.0, +1) + _steps(9500.0, 5, 10.0, -1) + _steps(12_000.0, 6, 1000.0, +1)
    + _steps(19_000.0, 4, 10.0, +1) + _steps(21_000.0, 5, 1000.0, -1) + _steps(27_000.0, 6, 10.0, -1)
    + _steps(29_000.0, 4, 1000.0, -1)
)
FRAMES = np.array([[0.6, 0.9, 0.4]])


def _approximate(rule: str, threshold: float = 5000.0) -> tuple[Irradiance, np.ndarray]:
    profile = interval_profile(STREAM, 1, t0_us=0.0, period_us=T, contrast_pos=C, contrast_neg=C)
    irradiance = approximate(
        profile.pixel, profile.t_us, profile.p, profile.first, profile.count, n_pixels=1, period_us=T,
        contrast_pos=C, contrast_neg=C, refractory_us=0.0, bounds_us=BOUNDS, frame_values=FRAMES,
        f=profile.f if rule == "spikes" else None, threshold_per_s=threshold,
    )
    return irradiance, profile.f


def _window_integrals(irradiance: Irradiance, samples: int = 30_000) -> np.ndarray:
    """∫ Î dt over each window on a fine midpoint grid (saturation units)."""
    out = []
    for j in range(3):
        width = BOUNDS[j + 1] - BOUNDS[j]
        phase = BOUNDS[j] + (np.arange(samples) + 0.5) * width / samples
        out.append(irradiance.value(np.zeros(samples, np.int64), phase).sum() * width / samples / 1e6)
    return np.array(out)


def test_the_scale_changes_at_the_end_of_each_strong_burst_and_fits_the_three_frames() -> None:
    irradiance, _ = _approximate("spikes")
    # one change per edge, at its burst's last event; never inside a burst or at slow shading
    np.testing.assert_array_equal(irradiance.change_us[0], [9540.0, 19_030.0, 27_050.0])
    pieces = irradiance.piece(np.zeros(5, np.int64), np.array([9539.0, 9540.0, 19_030.0, 30_000.0, 100.0]))
    np.testing.assert_array_equal(pieces, [2, 0, 1, 2, 2])  # the time before the first change is the last piece
    assert np.all(irradiance.scale[0] > 0) and len(set(np.round(irradiance.scale[0], 9))) == 3
    # three pieces, three windows: the frames are met exactly (up to the fit's 96-sample rule)
    np.testing.assert_allclose(_window_integrals(irradiance), FRAMES[0], rtol=0.01)


def test_without_strong_events_the_scale_is_one_least_squares_constant() -> None:
    irradiance, _ = _approximate("spikes", threshold=1e6)
    assert np.isnan(irradiance.change_us).all()
    assert np.ptp(irradiance.value(np.zeros(3, np.int64), np.array([100.0, 15_000.0, 30_000.0])) /
                  np.exp(irradiance.log_level(np.zeros(3, np.int64), np.array([100.0, 15_000.0, 30_000.0])))) == pytest.approx(0.0, abs=1e-9)
    integrals = _window_integrals(irradiance)
    # one value cannot meet three frames; it is their least-squares compromise, so the residual
    # is orthogonal to the shape of the integrals
    residual = integrals - FRAMES[0]
    assert np.abs(residual).max() > 0.05
    assert abs(residual @ integrals) < 1e-2 * (integrals @ integrals)  # measured 0.8 %: the fit integrates on 96 samples


def test_window_rule_takes_one_value_per_window() -> None:
    irradiance, _ = _approximate("windows")
    np.testing.assert_array_equal(irradiance.change_us[0], BOUNDS[:-1])
    np.testing.assert_array_equal(irradiance.piece(np.zeros(3, np.int64), np.array([0.0, T / 2, T - 1])), [0, 1, 2])
    np.testing.assert_allclose(_window_integrals(irradiance), FRAMES[0], rtol=0.01)


def test_the_rule_is_an_option_of_preprocessing(tmp_path: Path) -> None:
    with pytest.raises(UserError, match=r"^dualres: option scale_rule = 'median' must be one of windows, spikes$"):
        PreprocessOptions(scale_rule="median").check()
    path = tmp_path / "sphere.h5"
    simulate(SimulationConfig(scene="sphere", size=24, brdf="lambertian", refractory_us=0.0), path)
    capture = psfmt.read(path)
    windows = preprocess(capture, PreprocessOptions())
    spikes = preprocess(capture, PreprocessOptions(scale_rule="spikes"))
    # Î sets the importance samples (eq. 23) and the events' confidence, not which pairs are used
    assert windows.samples.phase_us.size != spikes.samples.phase_us.size
    np.testing.assert_array_equal(windows.events.t_us, spikes.events.t_us)
    assert not np.array_equal(windows.events.weight, spikes.events.weight)


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.cuda)])
def test_the_device_fit_of_the_scale_is_the_hosts(blobs_48: Path, device: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """The torch copy of the scale's fit (``irradiance_device``) held to numpy's on a simulated capture's
    super pixels, at the window bounds and at the spikes (pieces that wrap the period, pixels without
    events), and ``interp`` to ``numpy.interp`` at, between and beyond the knots."""
    import torch

    from pstoolkit_dualres.irradiance import SCALE_SAMPLES, _fit_scale
    from pstoolkit_dualres.irradiance_device import fit_scale_there, interp

    xp = np.array([0.0, 1.0, 1.5, 4.0])
    fp = np.array([2.0, -1.0, 3.0, 0.5])
    x = np.array([-1.0, 0.0, 0.3, 1.0, 1.2, 1.5, 3.9, 4.0, 9.0])
    torch_x, torch_xp, torch_fp = (torch.as_tensor(a, device=device) for a in (x, xp, fp))
    np.testing.assert_array_equal(interp(torch_x, torch_xp, torch_fp).cpu().numpy(), np.interp(x, xp, fp))
    pre = preprocess(psfmt.read(blobs_48), PreprocessOptions())
    values = np.stack([np.full(pre.event_height * pre.event_width, 0.2 + 0.1 * j) for j in range(3)], axis=1)
    for irradiance, fitted in ((pre.irradiance, values), (_approximate("spikes")[0], FRAMES)):
        host = _fit_scale(irradiance, fitted)
        there = fit_scale_there(irradiance, fitted, SCALE_SAMPLES, device)
        np.testing.assert_allclose(there, host, rtol=1e-9, atol=1e-12)
        assert np.all(np.isfinite(host)) and np.ptp(host) > 0
