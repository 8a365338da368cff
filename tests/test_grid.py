"""Frame↔event grid geometry (pstoolkit.grid): footprints, area weights and lookups."""

from __future__ import annotations

import numpy as np
import pytest

import psfmt
from pstoolkit.grid import default_affine, event_shape, footprints, frame_to_event, nearest_super_pixel, to_frames


@pytest.mark.parametrize(("frame", "scale"), [((8, 12), 0.5), ((9, 6), 1.0 / 3.0), ((10, 10), 0.4)])
def test_footprints_area_average_and_tile_the_frame(frame: tuple[int, int], scale: float) -> None:
    events = event_shape(*frame, scale)
    index, weight = footprints(events, frame, scale)
    assert index.shape == weight.shape and index.shape[0] == events[0] * events[1]
    np.testing.assert_allclose(weight.sum(axis=1), 1.0, atol=1e-12)  # an average of frame pixels
    covered = np.bincount(index.ravel(), weights=weight.ravel(), minlength=frame[0] * frame[1])
    # the event grid tiles the frame: each frame pixel's area is split among the event pixels over it,
    # each of which averages 1/s² frame pixels, so its weights add up to s²
    np.testing.assert_allclose(covered, scale * scale, atol=1e-12)


def test_the_default_affine_maps_centres_of_a_half_resolution_sensor() -> None:
    affine = default_affine(64, 128)
    np.testing.assert_array_equal(affine, psfmt.scale_affine(0.5))
    ue, ve = frame_to_event(affine, np.array([0.5, 126.5]), np.array([0.5, 126.5]))
    np.testing.assert_allclose(ue, [0.0, 63.0], atol=1e-12)
    super_pixel = nearest_super_pixel(affine, 4, 4, 2, 2)
    np.testing.assert_array_equal(super_pixel.reshape(4, 4), [[0, 0, 1, 1], [0, 0, 1, 1], [2, 2, 3, 3], [2, 2, 3, 3]])


def test_to_frames_interpolates_only_from_known_super_pixels() -> None:
    affine = default_affine(2, 4)
    values = np.array([[1.0], [2.0], [3.0], [5.0]])
    known = np.array([True, True, True, False])
    out, any_known = to_frames(values, known, affine, 4, 4, 2, 2)
    # the corner pixel under the unknown super pixel alone has no known neighbour
    np.testing.assert_array_equal(any_known, np.arange(16) != 15)
    assert out[0, 0] == pytest.approx(1.0)
    assert 1.0 <= out[any_known].min() and out[any_known].max() <= 3.0  # the unknown 5 never leaks in
