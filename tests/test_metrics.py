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
    assert stats == {"mae_deg": pytest.approx(45.0), "median_deg": pytest.approx(45.0), "below_10": pytest.approx(1 / 3), "below_20": pytest.approx(1 / 3), "below_30": pytest.approx(1 / 3), "n_pixels": 3}


def test_mean_is_of_angles_not_of_cosines_and_median_differs() -> None:
    stats = error_stats(np.array([0.0, 0.0, 5.0, 15.0, 25.0, 180.0]))
    assert stats["mae_deg"] == pytest.approx(225.0 / 6)
    assert stats["median_deg"] == pytest.approx(10.0)
    assert (stats["below_10"], stats["below_20"], stats["below_30"]) == (pytest.approx(0.5), pytest.approx(4 / 6), pytest.approx(5 / 6))


def test_bad_input_is_a_clear_error() -> None:
    with pytest.raises(UserError, match=r"normal maps of shape \(2, 3\) and \(3, 3\) cannot be compared"):
        angular_error_deg(np.zeros((2, 3)), np.zeros((3, 3)))
    with pytest.raises(UserError, match="mask of shape"):
        angular_error_deg(np.zeros((2, 2, 3)), np.zeros((2, 2, 3)), np.ones((3, 2), bool))
    with pytest.raises(UserError, match="no pixels to evaluate"):
        error_stats(np.full(4, np.nan))
