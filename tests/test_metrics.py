"""Angular error and its statistics at known angles."""

from __future__ import annotations

import numpy as np
import pytest

from pstoolkit.errors import UserError
from pstoolkit.metrics import angular_error_deg, error_stats


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
