"""``depth_error``: the least-squares scale and offset are found, the RMSE is in the truth's units,
non-finite pixels and pixels outside the mask are left out, and bad input is refused."""

from __future__ import annotations

import numpy as np
import pytest

from pstoolkit.errors import UserError
from pstoolkit.evaluation.metrics import DepthError, depth_error


def test_an_exact_scale_and_offset_are_recovered() -> None:
    truth = np.random.default_rng(0).normal(size=(8, 9))
    depth = (truth - 3.0) / -2.5  # another sign convention and unit
    error = depth_error(depth, truth, np.ones(truth.shape, dtype=bool))
    assert error.rmse == pytest.approx(0.0, abs=1e-12)
    assert (error.scale, error.offset, error.pixels) == (pytest.approx(-2.5), pytest.approx(3.0), 72)


def test_without_scale_only_the_offset_is_fitted() -> None:
    truth = np.array([[0.0, 1.0, 2.0, 3.0]])
    error = depth_error(2 * truth, truth, np.ones((1, 4), dtype=bool), scale=False)
    # residual of 2t + o − t = t + o, o = −mean(t) = −1.5: RMSE = std(t)
    assert isinstance(error, DepthError) and error.scale == 1.0 and error.offset == pytest.approx(-1.5)
    assert error.rmse == pytest.approx(np.std(truth[0]))


def test_only_finite_pixels_of_the_mask_count() -> None:
    truth = np.array([[1.0, 2.0, 3.0, 100.0, 5.0]])
    depth = np.array([[1.0, 2.0, 3.0, 4.0, np.nan]])
    error = depth_error(depth, truth, np.array([[True, True, True, False, True]]))
    assert error.pixels == 3 and error.rmse == pytest.approx(0.0, abs=1e-12)


def test_a_constant_depth_explains_nothing() -> None:
    truth = np.array([[1.0, 3.0]])
    error = depth_error(np.full((1, 2), 7.0), truth, np.ones((1, 2), dtype=bool))
    assert (error.scale, error.offset, error.rmse) == (0.0, 2.0, 1.0)


def test_bad_input_is_refused() -> None:
    with pytest.raises(UserError, match=r"depth \(2, 2\), truth \(2, 3\) and mask \(2, 3\) must be equal"):
        depth_error(np.zeros((2, 2)), np.zeros((2, 3)), np.ones((2, 3), dtype=bool))
    with pytest.raises(UserError, match="no pixels to compare"):
        depth_error(np.full((2, 2), np.nan), np.zeros((2, 2)), np.ones((2, 2), dtype=bool))
