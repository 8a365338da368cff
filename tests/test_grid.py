"""Frame↔event grid geometry (pstoolkit.grid): footprints, area weights and lookups."""

from __future__ import annotations

import numpy as np
import pytest

import psfmt
from pstoolkit.errors import UserError
from pstoolkit.grid import affine_footprints, default_affine, event_shape, footprints, frame_to_event, nearest_super_pixel, to_frames


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


@pytest.mark.parametrize(("frame", "scale"), [((8, 12), 0.5), ((9, 6), 1.0 / 3.0), ((10, 10), 0.4)])
def test_footprints_through_a_scale_affine_are_the_simulators(frame: tuple[int, int], scale: float) -> None:
    events = event_shape(*frame, scale)
    index, share = affine_footprints(psfmt.scale_affine(scale), events, frame)
    expected_index, expected_weight = footprints(events, frame, scale)
    np.testing.assert_array_equal(index, expected_index)
    np.testing.assert_allclose(share, expected_weight, atol=1e-12)  # every event pixel lies inside


def test_footprints_follow_a_calibrated_offset_and_per_axis_scale() -> None:
    # event pixels 1.5 frame pixels wide and 3 tall, the grid moved right by 1 and down by ½ a frame pixel
    affine = np.array([[1.5, 0.0, 0.25 + 1.0], [0.0, 3.0, 1.0 + 0.5]])
    index, share = affine_footprints(affine, (3, 4), (10, 8))
    dense = np.zeros((12, 80))
    np.add.at(dense, (np.repeat(np.arange(12), index.shape[1]), index.ravel()), share.ravel())
    # event pixel (0, 0) covers frame edges x ∈ [1, 2.5), y ∈ [0.5, 3.5)
    expected = np.zeros((10, 8))
    expected[0, 1], expected[1:3, 1], expected[3, 1] = 0.5 / 3, 1 / 3, 0.5 / 3
    expected[:, 2] = expected[:, 1] * 0.5
    expected[:, 1] *= 1.0 / 1.5
    expected[:, 2] *= 1.0 / 1.5
    np.testing.assert_allclose(dense[0].reshape(10, 8), expected, atol=1e-12)
    # the last column of event pixels reaches x ∈ [5.5, 7): inside; the last row y ∈ [6.5, 9.5): inside
    np.testing.assert_allclose(dense.sum(axis=1), 1.0, atol=1e-12)
    # a grid that reaches past the frame: the shares are those of the part inside
    # (x: edges [1, 3) and [3, 5); y: [-1, 1) and [1, 3))
    index, share = affine_footprints(np.array([[2.0, 0.0, 1.5], [0.0, 2.0, -0.5]]), (2, 2), (4, 4))
    np.testing.assert_allclose(share.sum(axis=1), [0.5, 0.25, 1.0, 0.5], atol=1e-12)


def test_a_mirrored_axis_reverses_the_footprints() -> None:
    mirror = np.array([[-2.0, 0.0, 7.0 - 0.5], [0.0, 2.0, 0.5]])  # event column 0 sees frame columns 7 and 6
    index, share = affine_footprints(mirror, (4, 4), (8, 8))
    straight_index, straight_share = affine_footprints(psfmt.scale_affine(0.5), (4, 4), (8, 8))
    v, u = np.divmod(index, 8)
    # frame column u seen mirrored is column 7 - u seen straight
    np.testing.assert_array_equal(np.sort(v * 8 + (7 - u), axis=1), straight_index)
    np.testing.assert_allclose(share, straight_share, atol=1e-12)


def test_a_rotating_affine_is_sampled_and_agrees_with_the_exact_shares() -> None:
    frame, events = (12, 16), (6, 8)
    exact_index, exact_share = affine_footprints(psfmt.scale_affine(0.5), events, frame)
    tilted = psfmt.scale_affine(0.5)
    tilted[0, 1] = 1e-12  # no visible rotation: the sampled path must give the exact shares
    index, share = affine_footprints(tilted, events, frame)
    np.testing.assert_array_equal(index, exact_index)
    np.testing.assert_allclose(share, exact_share, atol=1e-12)
    # a quarter turn: event pixel (v_e, u_e) sees the frame pixels of the transposed grid
    turn = np.array([[0.0, 2.0, 0.5], [2.0, 0.0, 0.5]])
    index, share = affine_footprints(turn, (8, 6), frame)
    np.testing.assert_array_equal(index.reshape(8, 6, -1), exact_index.reshape(6, 8, -1).transpose(1, 0, 2))
    np.testing.assert_allclose(share.sum(axis=1), 1.0)
    # 30°: every event pixel's shares sum to the part of it inside the frame, at most 1
    c, s = np.cos(np.pi / 6), np.sin(np.pi / 6)
    index, share = affine_footprints(np.array([[2 * c, -2 * s, 6.0], [2 * s, 2 * c, 0.0]]), events, frame)
    assert share.min() >= 0 and share.sum(axis=1).max() <= 1.0 + 1e-12 and (share.sum(axis=1) == 1.0).any()
    # a crafted affine whose pixels would span the frame: one line, nothing allocated
    for scale in (1e6, np.inf):
        with pytest.raises(UserError, match=r"^event→frame affine: an event pixel spans .* frame pixels along an axis \(at most 8\)$"):
            affine_footprints(np.array([[scale * c, -scale * s, 6.0], [scale * s, scale * c, 0.0]]), (3, 3), frame)

