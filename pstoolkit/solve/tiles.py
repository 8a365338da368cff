"""Spatial tiles of a capture: plan them, cut a capture to one, stitch the tiles' results (numpy only).

A solver whose unknowns are local (per-pixel values and low-frequency maps) solves a large capture
tile by tile: each tile is a rectangle of frame pixels (its *core*) grown by ``overlap_px`` on every
side that has a neighbour (its *crop*), cut out of the capture with the event pixels that see it
(``crop_capture``), solved on its own, and blended back (``Stitcher``) with weights that fall
linearly from 1 to 0 across a band of ``overlap_px`` centred on the boundary between two cores: the
outer half of each overlap, where a tile lacks its neighbours' data, never counts, and no pixel
changes source abruptly.

    plan = plan_tiles(height, width, tile_px=512, overlap_px=32)
    stitcher = Stitcher(height, width)
    for tile in plan:
        stitcher.add(tile, solve(crop_capture(capture, tile)))
    result = stitcher.result()
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

import psfmt
from pstoolkit.errors import UserError
from pstoolkit.grid import default_affine, frame_to_event
from pstoolkit.solve.base import SolverResult

# Core sizes are multiples of this (frame pixels), so that at the usual 1/2 and 1/4 event scales a
# core boundary falls on an event pixel boundary.
ALIGN_PX = 8
# Events filtered at a time while streaming a tile's share of the stream.
STREAM_EVENTS = 1 << 22


@dataclass(frozen=True)
class Tile:
    """One tile of an H×W frame: its ``index`` in the plan of ``rows`` × ``cols`` tiles, the core
    ``[top, bottom) × [left, right)`` it owns, and the crop ``[crop_top, crop_bottom) ×
    [crop_left, crop_right)`` it is solved on (frame pixels)."""

    index: int
    rows: int
    cols: int
    top: int
    bottom: int
    left: int
    right: int
    crop_top: int
    crop_bottom: int
    crop_left: int
    crop_right: int

    @property
    def crop_shape(self) -> tuple[int, int]:
        return self.crop_bottom - self.crop_top, self.crop_right - self.crop_left

    @property
    def crop_pixels(self) -> int:
        h, w = self.crop_shape
        return h * w

    def label(self) -> str:
        """``row,col`` of the tile in the plan, for messages."""
        return f"{self.index // self.cols},{self.index % self.cols}"


def _cuts(length: int, count: int) -> list[int]:
    """``count`` + 1 boundaries splitting [0, length) into cores of near-equal size, inner ones on
    multiples of ``ALIGN_PX`` where the length allows."""
    step = length / count
    inner = [int(round(i * step / ALIGN_PX)) * ALIGN_PX for i in range(1, count)]
    return [0, *inner, length]


def _down(x: int) -> int:
    return x // ALIGN_PX * ALIGN_PX


def _up(x: int) -> int:
    return -(-x // ALIGN_PX) * ALIGN_PX


MAX_TILES = 4096
"""Most tiles one frame is cut into (a 65 536² frame in 1024² tiles): each tile is a task with its own
copy of the capture's lights and a crop's overhead, so a tiny ``tile_px`` would fill memory with tasks."""


def plan_tiles(height: int, width: int, *, tile_px: int, overlap_px: int) -> list[Tile]:
    """Tiles over an H×W frame whose cores are at most about ``tile_px`` on a side (the fewest that
    are), each crop reaching at least ``overlap_px`` beyond its core where there is a neighbour (its
    bounds rounded out to multiples of ``ALIGN_PX``, so that a crop of an event sensor at 1/2, 1/4 or
    1/8 of the frame's resolution starts and ends on event pixel boundaries). One tile
    (core and crop the whole frame) when the frame fits. UserError for a non-positive ``tile_px``,
    a negative ``overlap_px``, or an overlap wider than a core (the blending bands would meet), or more than ``MAX_TILES`` tiles."""
    if tile_px <= 0:
        raise UserError(f"tile_px = {tile_px}: a tile needs a positive size in frame pixels")
    if overlap_px < 0:
        raise UserError(f"overlap_px = {overlap_px}: must not be negative")
    rows, cols = max(1, math.ceil(height / tile_px)), max(1, math.ceil(width / tile_px))
    if rows * cols > MAX_TILES:
        raise UserError(f"tile_px = {tile_px}: cuts the {width}×{height} frame into {rows * cols} tiles, over {MAX_TILES}; use larger tiles")
    row_cuts, col_cuts = _cuts(height, rows), _cuts(width, cols)
    # each core boundary blends over a band of overlap_px centred on it: a core must hold both halves
    cores = [int(d) for cuts, n in ((row_cuts, rows), (col_cuts, cols)) if n > 1 for d in np.diff(cuts)]
    if cores and overlap_px > min(cores):
        raise UserError(f"overlap_px = {overlap_px}: wider than a tile's core ({min(cores)} px); use larger tiles or less overlap")
    tiles = []
    for r in range(rows):
        for c in range(cols):
            top, bottom, left, right = row_cuts[r], row_cuts[r + 1], col_cuts[c], col_cuts[c + 1]
            tiles.append(Tile(
                index=r * cols + c, rows=rows, cols=cols, top=top, bottom=bottom, left=left, right=right,
                crop_top=max(0, _down(top - overlap_px)), crop_bottom=min(height, _up(bottom + overlap_px)),
                crop_left=max(0, _down(left - overlap_px)), crop_right=min(width, _up(right + overlap_px)),
            ))
    return tiles


def event_window(tile: Tile, affine: np.ndarray, event_height: int, event_width: int) -> tuple[int, int, int, int]:
    """The event pixels ``[top, bottom) × [left, right)`` that see the tile's crop through the
    event→frame ``affine``: exactly those covering it when the crop's edges fall on event pixel
    edges (an aligned crop, ``plan_tiles``, and a scale affine, ``psfmt.scale_affine``), so the crop
    is again a capture of that geometry; otherwise the bounding box widened by one pixel, so that
    every frame pixel has its nearest super pixel inside. Clipped to the sensor."""
    v = np.array([tile.crop_top, tile.crop_top, tile.crop_bottom, tile.crop_bottom], dtype=np.float64) - 0.5
    u = np.array([tile.crop_left, tile.crop_right, tile.crop_left, tile.crop_right], dtype=np.float64) - 0.5
    ue, ve = frame_to_event(affine, u, v)
    # event pixel edges: centres ± ½
    edges = np.array([ue.min(), ue.max(), ve.min(), ve.max()]) + 0.5
    if np.allclose(edges, np.rint(edges), atol=1e-6):
        left, right, top, bottom = (int(x) for x in np.rint(edges))
    else:
        left, right = int(math.floor(edges[0])) - 1, int(math.ceil(edges[1])) + 1
        top, bottom = int(math.floor(edges[2])) - 1, int(math.ceil(edges[3])) + 1
    return max(0, top), min(event_height, bottom), max(0, left), min(event_width, right)


def _region_events(events: psfmt.Events, window: tuple[int, int, int, int]) -> psfmt.EventArray:
    """The events inside the event-pixel ``window`` (top, bottom, left, right), moved to its origin,
    streamed in bounded chunks from the stream (a file's chunks are read one at a time)."""
    top, bottom, left, right = window
    parts = []
    for chunk in events.chunks(STREAM_EVENTS):
        keep = (chunk.x >= left) & (chunk.x < right) & (chunk.y >= top) & (chunk.y < bottom)
        if keep.any():
            part = chunk[keep]
            parts.append(psfmt.EventArray(part.x - left, part.y - top, part.t, part.p))
    return psfmt.EventArray.concatenate(parts)


def crop_capture(capture: psfmt.Capture, tile: Tile) -> psfmt.Capture:
    """The capture seen through the tile's crop, held in memory: the frames' crop (only it is read
    from a file), the events of the pixels that see it (``event_window``) moved to the window's origin,
    the event→frame affine and a perspective camera's principal point moved with them, the lights,
    sensor calibration and the ground truth's crop. Captures without frames or events keep None."""
    cal = capture.calibration
    rows, cols = slice(tile.crop_top, tile.crop_bottom), slice(tile.crop_left, tile.crop_right)
    frames = None
    if capture.frames is not None:
        f = capture.frames
        frames = replace(f, data=np.asarray(f.data[:, rows, cols]))
    events, affine = None, cal.event_to_frame
    if capture.events is not None and capture.frames is not None:
        ev = capture.events
        full = default_affine(ev.width, capture.frames.width) if cal.event_to_frame is None else cal.event_to_frame
        top, bottom, left, right = event_window(tile, full, ev.height, ev.width)
        events = psfmt.Events(right - left, bottom - top, _region_events(ev, (top, bottom, left, right)))
        # frame' = A·(event' + e0) + b − f0
        affine = full.copy()
        affine[:, 2] += full[:, :2] @ np.array([left, top], dtype=np.float64) - np.array([tile.crop_left, tile.crop_top], dtype=np.float64)
    intrinsics = cal.intrinsics
    if intrinsics is not None:
        intrinsics = intrinsics.copy()
        intrinsics[0, 2] -= tile.crop_left
        intrinsics[1, 2] -= tile.crop_top
    truth = capture.ground_truth
    if truth is not None:
        truth = psfmt.GroundTruth(**{
            name: (None if value is None else np.asarray(value)[rows, cols])
            for name, value in ((n, getattr(truth, n)) for n in ("normal", "mask", "albedo", "depth"))
        }, materials={k: np.asarray(v)[rows, cols] for k, v in truth.materials.items()})
    return psfmt.Capture(
        frames=frames, events=events, lights=capture.lights,
        calibration=replace(cal, event_to_frame=affine, intrinsics=intrinsics),
        ground_truth=truth, description=f"tile {tile.label()} of {capture.path or 'a capture'}",
        creator=capture.creator, creator_version=capture.creator_version, format_version=capture.format_version,
    )


def _ramp(n: int, start: int, core: tuple[int, int], overlap_px: int, ends: tuple[bool, bool]) -> np.ndarray:
    """(n,) blending weights along one axis of a crop starting at ``start``: 1 inside the core
    [core[0], core[1]), falling linearly to 0 over the ``overlap_px``-wide band centred on each core
    boundary that has a neighbour (``ends``: the low and the high side)."""
    x = np.arange(start, start + n, dtype=np.float64) + 0.5
    w = np.ones(n)
    if overlap_px > 0:
        if ends[0]:
            w = np.minimum(w, np.clip((x - (core[0] - overlap_px / 2)) / overlap_px, 0.0, 1.0))
        if ends[1]:
            w = np.minimum(w, np.clip(((core[1] + overlap_px / 2) - x) / overlap_px, 0.0, 1.0))
    return w


def blend_weights(tile: Tile, overlap_px: int) -> np.ndarray:
    """(crop H, crop W) float64 weights of the tile's pixels in the stitched result; over all tiles
    they sum to 1 at every frame pixel."""
    h, w = tile.crop_shape
    r, c = divmod(tile.index, tile.cols)
    rows = _ramp(h, tile.crop_top, (tile.top, tile.bottom), overlap_px, (r > 0, r < tile.rows - 1))
    cols = _ramp(w, tile.crop_left, (tile.left, tile.right), overlap_px, (c > 0, c < tile.cols - 1))
    return rows[:, None] * cols[None, :]


class Stitcher:
    """Accumulates tiles' results into one H×W result: normals and maps as weighted means over the
    tiles that hold the pixel in their mask (normals renormalised), the mask where any does."""

    def __init__(self, height: int, width: int, overlap_px: int) -> None:
        self.height, self.width, self.overlap_px = height, width, overlap_px
        # float32 sums: a megapixel frame's maps are a dozen channels, and weights in [0, 1] lose nothing
        self._normal = np.zeros((height, width, 3), dtype=np.float32)
        self._weight = np.zeros((height, width), dtype=np.float32)
        self._maps: dict[str, np.ndarray] = {}
        self.diagnostics: list[dict[str, object]] = []

    def add(self, tile: Tile, result: SolverResult) -> None:
        """Blend in one tile's result (its maps at the crop's size); ValueError for a result of
        another size."""
        if result.normal.shape[:2] != tile.crop_shape:
            raise ValueError(f"tile {tile.label()}: result of {result.normal.shape[:2]}, expected {tile.crop_shape}")
        rows, cols = slice(tile.crop_top, tile.crop_bottom), slice(tile.crop_left, tile.crop_right)
        weight = (blend_weights(tile, self.overlap_px) * result.mask).astype(np.float32)
        self._normal[rows, cols] += weight[..., None] * result.normal
        self._weight[rows, cols] += weight
        for name, value in result.maps.items():
            value = np.asarray(value, dtype=np.float32)
            if name not in self._maps:
                self._maps[name] = np.zeros((self.height, self.width) + value.shape[2:], dtype=np.float32)
            self._maps[name][rows, cols] += weight.reshape(weight.shape + (1,) * (value.ndim - 2)) * value
        self.diagnostics.append({"tile": tile.label(), **result.diagnostics})

    def result(self, diagnostics: dict[str, object]) -> SolverResult:
        """The stitched result with ``diagnostics`` (the tiles' own under ``tiles``)."""
        mask = self._weight > 0
        safe = np.where(mask, self._weight, 1.0)
        normal = self._normal / safe[..., None]
        norm = np.linalg.norm(normal, axis=-1, keepdims=True)
        normal = np.where(norm > 0, normal / np.where(norm > 0, norm, 1.0), 0.0)
        maps = {name: (value / safe.reshape(safe.shape + (1,) * (value.ndim - 2))).astype(np.float32)
                for name, value in self._maps.items()}
        return SolverResult(normal=normal.astype(np.float32), mask=mask, maps=maps,
                            diagnostics={**diagnostics, "tiles": self.diagnostics})

