"""Angular error and its statistics at known angles."""

from __future__ import annotations

import numpy as np
import pytest

from pstoolkit.errors import UserError
from pstoolkit.evaluation.metrics import angular_error_deg, error_stats, highlight_band, rim_band


def test_known_angles() -> None:
    gt = np.tile([0.0, 0.0, 1.0], (1, 5, 1))
    est = np.array([[[0, 0, 2.0], [1, 0, 0], [0, 0, -1], [0, 1, 1], [0, 0, 0]]])
    errors = angular_error_deg(est, gt)
    np.testing.assert_allclose(errors, [[0, 90, 180, 45, 90]], atol=1e-12)


def test_small_angles_are_resolved() -> None:
    angle = np.deg2rad(0.005)
    errors = angular_error_deg(np.array([[np.sin(angle), 0, np.cos(angle)]]), np.array([[0.0, 0, 1]]))
    np.testing.assert_allclose(errors, [0.005], rtol=1e-3)


def test_mask_gives_nan_outside_and_stats_skip_it() -> None:
    gt = np.tile([0.0, 0.0, 1.0], (2, 2, 1))
    est = np.array([[[0, 0, 1.0], [1, 0, 0]], [[0, 1, 1], [0, 0, -1]]])
    mask = np.array([[True, True], [True, False]])
    errors = angular_error_deg(est, gt, mask)
    assert np.isnan(errors[1, 1])
    stats = error_stats(errors)
    assert stats == {
        "mae_deg": pytest.approx(45.0),
        "median_deg": pytest.approx(45.0),
        "p90_deg": pytest.approx(81.0),  # linear between the sorted 45° and 90° at 0.8
        "below_11_25": pytest.approx(1 / 3),
        "below_22_5": pytest.approx(1 / 3),
        "below_30": pytest.approx(1 / 3),
        "n_pixels": 3,
        "coverage": 1.0,
        "mae_solved_deg": pytest.approx(45.0),
    }


def test_mean_is_of_angles_not_of_cosines_and_median_differs() -> None:
    stats = error_stats(np.array([0.0, 0.0, 5.0, 15.0, 25.0, 180.0]))
    assert stats["mae_deg"] == pytest.approx(225.0 / 6)
    assert stats["median_deg"] == pytest.approx(10.0)
    assert (stats["below_11_25"], stats["below_22_5"], stats["below_30"]) == (pytest.approx(0.5), pytest.approx(4 / 6), pytest.approx(5 / 6))


def test_unsolved_pixels_count_90_degrees_and_against_the_coverage() -> None:
    """A solver that leaves 4 of 10 mask pixels out (zero normal: 90°) and is exact elsewhere: MAE 36°,
    coverage 60 %, MAE of the solved pixels 0°; the pixel outside the mask counts nowhere."""
    gt = np.tile([0.0, 0.0, 1.0], (1, 11, 1))
    est = gt.copy()
    est[0, 6:10] = 0.0
    est[0, 10] = [1.0, 0.0, 0.0]
    mask = np.arange(11)[None, :] < 10
    solved = np.any(est != 0, axis=-1)
    stats = error_stats(angular_error_deg(est, gt, mask), solved)
    assert stats["mae_deg"] == pytest.approx(36.0) and stats["median_deg"] == pytest.approx(0.0)
    assert stats["coverage"] == pytest.approx(0.6) and stats["mae_solved_deg"] == pytest.approx(0.0, abs=1e-6)
    assert stats["below_30"] == pytest.approx(0.6) and stats["n_pixels"] == 10
    nothing = error_stats(angular_error_deg(np.zeros_like(gt), gt, mask), np.zeros((1, 11), bool))
    assert nothing["coverage"] == 0.0 and nothing["mae_solved_deg"] is None and nothing["mae_deg"] == pytest.approx(90.0)


def test_bad_input_is_a_clear_error() -> None:
    with pytest.raises(UserError, match=r"normal maps of shape \(2, 3\) and \(3, 3\) cannot be compared"):
        angular_error_deg(np.zeros((2, 3)), np.zeros((3, 3)))
    with pytest.raises(UserError, match="mask of shape"):
        angular_error_deg(np.zeros((2, 2, 3)), np.zeros((2, 2, 3)), np.ones((3, 2), bool))
    with pytest.raises(UserError, match="no pixels to evaluate"):
        error_stats(np.full(4, np.nan))
    with pytest.raises(UserError, match=r"^solved map of 3 pixels does not fit an error map of 4$"):
        error_stats(np.zeros(4), np.ones(3, bool))


def test_the_rim_band_is_the_outer_share_of_a_disc() -> None:
    v, u = np.mgrid[0:101, 0:101]
    mask = (u - 50) ** 2 + (v - 50) ** 2 < 40**2
    band = rim_band(mask)
    radius = np.hypot(u - 50, v - 50)[band]
    assert radius.min() > 40 * 0.9 and band.sum() > 0.05 * mask.sum()  # the outer 2 px of a 40 px disc


def test_the_highlight_band_follows_the_mirror_direction() -> None:
    # a sphere under a light circling at 45° elevation: the highlight runs along a ring of normals
    # halfway between the light and the view, n_z = cos(22.5°)
    v, u = np.mgrid[0:81, 0:81]
    x, y = (u - 40) / 38.0, (40 - v) / 38.0
    mask = x**2 + y**2 < 1
    normal = np.dstack([x, y, np.sqrt(np.clip(1 - x**2 - y**2, 0, None))])
    azimuth = np.linspace(0, 2 * np.pi, 180, endpoint=False)
    directions = np.stack([np.cos(azimuth) * np.cos(np.pi / 4), np.sin(azimuth) * np.cos(np.pi / 4), np.full(180, np.sin(np.pi / 4))], axis=-1)
    band = highlight_band(normal, mask, directions, roughness=0.3)
    tilt = np.degrees(np.arccos(normal[..., 2]))[band]
    assert abs(np.median(tilt) - 22.5) < 1.5 and tilt.min() > 14 and tilt.max() < 31  # measured 23.3°, 15.0° to 30.0°
    assert highlight_band(normal, mask, directions, roughness=0.6).sum() > band.sum()  # a rougher lobe is wider
