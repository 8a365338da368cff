"""Each event pixel's contrast thresholds, fitted with the normals (``pstoolkit_dualres.thresholds``,
option ``threshold_sigma``)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.ndimage import median_filter

import psfmt
from pstoolkit.evaluation.metrics import angular_error_deg
from pstoolkit.optics.brdf import GGX
from pstoolkit.sim.config import SimulationConfig
from pstoolkit.sim.simulator import simulate
from pstoolkit.solve.api import solve_capture
from pstoolkit_dualres.fields import PyramidField
from pstoolkit_dualres.preprocess import PreprocessOptions, preprocess
from pstoolkit_dualres.problem import build_problem
from pstoolkit_dualres.reflectance import FitModel
from pstoolkit_dualres.solver import threshold_sigma
from pstoolkit_dualres.thresholds import NEIGHBOURHOOD, fit_thresholds


def test_the_pixels_thresholds_are_found_relative_to_their_neighbours(sphere_48: Path) -> None:
    """The sphere fitted at its true normals, every event pixel's C⁺ and C⁻ drawn 13 % apart (its
    pairs' nominal thresholds 1/g of what the light did): the balance the fit finds follows the drawn
    one; with the common scale too, the gains follow the drawn ones taken relative to their 3 × 3
    neighbourhood's median; the targets follow the gains."""
    capture = psfmt.read(sphere_48)
    pre = preprocess(capture, PreprocessOptions())
    problem = build_problem(pre, capture.calibration.view_direction, device="cpu")
    geometry, events = problem.geometry, problem.events
    model = FitModel(GGX())
    truth = torch.as_tensor(np.asarray(capture.ground_truth.normal).reshape(-1, 3)[geometry.pixels], dtype=torch.float32)
    field = PyramidField((geometry.height, geometry.width), geometry.pixels, truth, model.pixel_raw_from(geometry.init_albedo),
                         geometry.event_shape, geometry.grid_taps, model.raw_init("smooth"))
    shape = (pre.event_height, pre.event_width)
    drawn = np.exp(np.random.default_rng(7).normal(0.0, 0.13, (2, shape[0] * shape[1])))
    src = events.source
    src["rise"], src["fall"] = src["rise"] / drawn[0][src["pixel"]], src["fall"] / drawn[1][src["pixel"]]
    events.apply_thresholds(np.ones(drawn.shape[1]), np.ones(drawn.shape[1]))
    usable = events.usable.numpy()
    seen = [np.bincount(src["pixel"][usable][src[part][usable] > 0], minlength=drawn.shape[1]) >= 3 for part in ("rise", "fall")]
    both = seen[0] & seen[1]
    assert both.sum() > 100
    # balance: g⁺ = e^d, g⁻ = e^−d with d half the log ratio the sensor drew
    balance = fit_thresholds(problem, field, model, shape, 0.03, pre.contrast_pos, pre.contrast_neg)
    d, true_d = np.log(balance.gain_pos), 0.5 * np.log(drawn[0] / drawn[1])
    np.testing.assert_allclose(balance.gain_pos * balance.gain_neg, 1.0)
    assert np.corrcoef(d[both], true_d[both])[0, 1] > 0.9
    assert np.median(np.abs(d[both] - true_d[both])) < 0.04
    # both: each gain, relative to its neighbourhood's median
    gains = fit_thresholds(problem, field, model, shape, 0.03, pre.contrast_pos, pre.contrast_neg, common=True)
    for fitted, true, known in ((gains.gain_pos, drawn[0], seen[0]), (gains.gain_neg, drawn[1], seen[1])):
        relative = np.exp(np.log(true) - median_filter(np.log(true).reshape(shape), size=NEIGHBOURHOOD, mode="nearest").ravel())
        assert np.corrcoef(fitted[known], relative[known])[0, 1] > 0.9
        assert np.median(np.abs(fitted[known] - relative[known])) < 0.05
    events.apply_thresholds(gains.gain_pos, gains.gain_neg)
    pixel = src["pixel"]
    np.testing.assert_allclose(events.target.numpy(), src["rise"] * gains.gain_pos[pixel] - src["fall"] * gains.gain_neg[pixel],
                               rtol=1e-5, atol=1e-6)


def test_the_spread_comes_from_the_option_or_the_captures_record(blobs_48: Path) -> None:
    capture = psfmt.read(blobs_48)
    assert threshold_sigma(capture, 0.02) == 0.02
    assert (capture.calibration.sensor_model or {}).get("contrast_sigma", 0.0) == 0.0
    assert threshold_sigma(capture, 0.0) == 0.0
    recorded = replace(capture, calibration=replace(capture.calibration, sensor_model={"name": "evk4", "contrast_sigma": 0.03}))
    assert threshold_sigma(recorded, 0.0) == 0.03
    assert threshold_sigma(recorded, 0.05) == 0.05
    crafted = replace(capture, calibration=replace(capture.calibration, sensor_model={"name": "x", "contrast_sigma": float("nan")}))
    assert threshold_sigma(crafted, 0.0) == 0.0


@pytest.fixture(scope="module")
def spread_48(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Blobs at 48 px through pixels whose thresholds spread by σ = 0.03 around C = 0.2231 (the
    EVK4-like preset's, without its noise)."""
    path = tmp_path_factory.mktemp("spread") / "blobs.h5"
    simulate(SimulationConfig(scene="blobs", size=48, seed=0, contrast=0.2231, contrast_sigma=0.03), path)
    return path


def test_fitting_the_thresholds_undoes_their_spread(spread_48: Path) -> None:
    """With the capture's recorded spread the fit estimates the pixels' thresholds — their balance by
    default, their common scale too with ``thresholds=both`` — and the normals' error falls below the
    fit's with the nominal ones."""
    capture = psfmt.read(spread_48)
    truth = capture.ground_truth
    errors, spreads = {}, {}
    for fit in ("nominal", "balance", "both"):
        result = solve_capture(capture, "dualres", thresholds=fit, epochs=80)
        errors[fit] = float(np.mean(angular_error_deg(result.normal, truth.normal, truth.mask)[np.asarray(truth.mask)]))
        assert result.diagnostics["threshold_sigma"] == (0.0 if fit == "nominal" else 0.03)
        spreads[fit] = result.diagnostics["thresholds"]
    assert spreads["nominal"] is None
    assert spreads["balance"]["gain_pos_p95"] - spreads["balance"]["gain_pos_p5"] > 0.15
    assert errors["balance"] < 0.93 * errors["nominal"]
    assert errors["both"] < 0.85 * errors["nominal"]
