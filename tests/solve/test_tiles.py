"""Spatial tiles (``pstoolkit.solve.tiles``): plans cover the frame with aligned cores, the blending
weights sum to one everywhere, a crop carries exactly the frames and events of its pixels with the
affine moved along, and stitching returns what the tiles said."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

import psfmt
from pstoolkit.errors import UserError
from pstoolkit.grid import frame_to_event, nearest_super_pixel
from pstoolkit.solve.base import SolverResult
from pstoolkit.solve.tiled import eta_text
from pstoolkit.solve.tiles import ALIGN_PX, Stitcher, blend_weights, crop_capture, event_window, plan_tiles


@pytest.mark.parametrize(("height", "width", "tile_px", "overlap_px"), [(100, 130, 40, 8), (64, 64, 32, 0), (50, 30, 64, 4)])
def test_plans_cover_the_frame_once_with_aligned_cores_and_blending_weights_summing_to_one(
    height: int, width: int, tile_px: int, overlap_px: int
) -> None:
    tiles = plan_tiles(height, width, tile_px=tile_px, overlap_px=overlap_px)
    owners = np.zeros((height, width), dtype=int)
    total = np.zeros((height, width))
    for tile in tiles:
        owners[tile.top : tile.bottom, tile.left : tile.right] += 1
        assert tile.bottom - tile.top <= tile_px + ALIGN_PX and tile.right - tile.left <= tile_px + ALIGN_PX
        for cut in (tile.top, tile.bottom, tile.left, tile.right):
            assert cut % ALIGN_PX == 0 or cut in (height, width)
        assert tile.crop_top == max(0, tile.top - overlap_px) and tile.crop_right == min(width, tile.right + overlap_px)
        total[tile.crop_top : tile.crop_bottom, tile.crop_left : tile.crop_right] += blend_weights(tile, overlap_px)
    assert (owners == 1).all()
    np.testing.assert_allclose(total, 1.0, atol=1e-12)
    assert len(tiles) == -(-height // tile_px) * -(-width // tile_px)


def test_blending_ignores_the_outer_half_of_each_overlap_and_ramps_across_the_seam() -> None:
    left, right = plan_tiles(16, 64, tile_px=32, overlap_px=8)
    w = blend_weights(left, 8)[0]
    assert w.shape == (40,) and (w[:28] == 1).all() and (w[36:] == 0).all()
    np.testing.assert_allclose(w[28:36], 1 - (np.arange(8) + 0.5) / 8)


@pytest.mark.parametrize(("overlap_px", "message"), [(-1, "must not be negative"), (33, "wider than a tile's core")])
def test_impossible_plans_are_refused(overlap_px: int, message: str) -> None:
    with pytest.raises(UserError, match=message):
        plan_tiles(64, 64, tile_px=32, overlap_px=overlap_px)
    with pytest.raises(UserError, match="positive size"):
        plan_tiles(64, 64, tile_px=0, overlap_px=0)


def test_a_crop_holds_the_frames_and_events_of_its_pixels_and_the_affine_moves_with_them(blobs_48: Path) -> None:
    with psfmt.read(blobs_48) as capture:
        full_events = capture.events.read()
        affine = capture.calibration.event_to_frame
        frames = np.asarray(capture.frames.data)
        tile = plan_tiles(48, 48, tile_px=24, overlap_px=8)[3]
        crop = crop_capture(capture, tile)
        top, bottom, left, right = event_window(tile, affine, capture.events.height, capture.events.width)
    np.testing.assert_array_equal(crop.frames.data, frames[:, tile.crop_top : tile.crop_bottom, tile.crop_left : tile.crop_right])
    assert (crop.events.height, crop.events.width) == (bottom - top, right - left)
    inside = (full_events.x >= left) & (full_events.x < right) & (full_events.y >= top) & (full_events.y < bottom)
    events = crop.events.read()
    assert len(events) == int(inside.sum()) > 0
    np.testing.assert_array_equal(events.x, full_events.x[inside] - left)
    np.testing.assert_array_equal(events.t, full_events.t[inside])
    # an event pixel maps to the same frame point through either affine, shifted by the crop origin
    ue, ve = np.array([0.0, 3.0]), np.array([0.0, 5.0])
    moved = crop.calibration.event_to_frame
    here = moved[:, :2] @ np.stack([ue, ve]) + moved[:, 2:]
    there = affine[:, :2] @ np.stack([ue + left, ve + top]) + affine[:, 2:]
    np.testing.assert_allclose(here, there - np.array([[tile.crop_left], [tile.crop_top]]))
    # every frame pixel of the crop has its nearest super pixel inside the window (none is clipped)
    h, w = tile.crop_shape
    v, u = np.mgrid[0:h, 0:w].astype(float)
    ue_all, ve_all = frame_to_event(moved, u, v)
    assert ue_all.min() >= -0.5 and ve_all.min() >= -0.5
    assert ue_all.max() <= right - left - 0.5 and ve_all.max() <= bottom - top - 0.5
    assert nearest_super_pixel(moved, h, w, bottom - top, right - left).max() < (bottom - top) * (right - left)
    assert crop.ground_truth.normal.shape == (h, w, 3)


def test_a_perspective_cameras_principal_point_moves_with_the_crop(blobs_48: Path) -> None:
    with psfmt.read(blobs_48) as capture:
        k = np.array([[60.0, 0.0, 24.0], [0.0, 60.0, 23.5], [0.0, 0.0, 1.0]])
        capture.calibration = replace(capture.calibration, camera_model="perspective", intrinsics=k)
        tile = plan_tiles(48, 48, tile_px=24, overlap_px=8)[1]
        crop = crop_capture(capture, tile)
    np.testing.assert_allclose(crop.calibration.intrinsics, [[60, 0, 24 - tile.crop_left], [0, 60, 23.5 - tile.crop_top], [0, 0, 1]])
    assert crop.calibration.camera_model == "perspective" and capture.calibration.intrinsics[0, 2] == 24.0


def test_stitching_tiles_that_agree_returns_their_values_and_tiles_that_differ_blend_smoothly() -> None:
    tiles = plan_tiles(32, 48, tile_px=16, overlap_px=8)
    stitcher = Stitcher(32, 48, 8)
    for tile in tiles:
        h, w = tile.crop_shape
        normal = np.zeros((h, w, 3), np.float32)
        normal[..., 2] = 1
        albedo = np.full((h, w, 3), float(tile.index), np.float32)
        stitcher.add(tile, SolverResult(normal=normal, mask=np.ones((h, w), bool), maps={"albedo": albedo}, diagnostics={"n": 1}))
    result = stitcher.result({"tiling": {}})
    np.testing.assert_allclose(result.normal[..., 2], 1.0, rtol=1e-6)
    assert result.mask.all() and len(result.diagnostics["tiles"]) == len(tiles)
    albedo = result.maps["albedo"][..., 0]
    # inside a core away from seams a tile's own value; across a seam no step larger than the ramp's
    assert albedo[2, 2] == 0 and albedo[30, 46] == len(tiles) - 1
    assert np.abs(np.diff(albedo, axis=1)).max() <= (1 + 1e-6) / 8 + 1e-6


def test_eta_text() -> None:
    assert eta_text(0, 4, 10.0) == "tile 0/4"
    assert eta_text(1, 4, 30.0) == "tile 1/4, ETA 1:30"
    assert eta_text(4, 4, 99.0) == "tile 4/4"
