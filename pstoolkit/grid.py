"""Geometry between the frame grid and the event grid, written once for the simulator, the solvers,
the converters and calibration (numpy only).

Conventions (spec/hybrid-capture.md, ``/calibration/event_to_frame``): a (2, 3) affine maps event
pixel centres to frame pixel coordinates; without a calibration the two cameras see the same field
of view, ``default_affine``. The simulator's event pixel i covers frame pixel edges [i/s, (i+1)/s)
along each axis for ``s`` event pixels per frame pixel (``psfmt.scale_affine(s)``), and its
irradiance is the area average of the frame pixels it covers (``area_weights``, ``footprints``);
a calibrated rig's affine (any scale and offset per axis, or a rotation) gives the solvers the same
averages through ``affine_footprints``.
"""

from __future__ import annotations

import numpy as np

import psfmt
from pstoolkit.errors import UserError

# overlaps this thin are the rounding of coinciding edges, not a share of a pixel
SLIVER_PX = 1e-9
# samples a frame pixel a side for a rotating affine's footprints: shares to ~1/16 of a pixel
FOOTPRINT_SAMPLES_PER_PX = 4
# samples held at once while counting them (32 MB of int64)
FOOTPRINT_BLOCK_SAMPLES = 1 << 22
# the widest event pixel, in frame pixels along a frame axis, that footprints are made for: rigs
# sample at 1/2 to 1/4 of the frame's resolution, and a crafted affine's pixel could span the frame
MAX_FOOTPRINT_EXTENT_PX = 8.0


def default_affine(event_width: int, frame_width: int) -> np.ndarray:
    """(2, 3) event→frame affine of an event sensor ``event_width`` pixels wide that sees the same
    field of view as a frame ``frame_width`` pixels wide."""
    return psfmt.scale_affine(event_width / frame_width)


def event_shape(height: int, width: int, event_scale: float) -> tuple[int, int]:
    """Event sensor (height, width) for a frame of height×width at ``event_scale`` event pixels per
    frame pixel (rounded, at least 1)."""
    return max(1, int(round(height * event_scale))), max(1, int(round(width * event_scale)))


def area_weights(n_event: int, n_frame: int, event_scale: float) -> np.ndarray:
    """(n_event, n_frame) weights that area-average frame pixels onto one axis of the event grid of
    ``psfmt.scale_affine(event_scale)``: event pixel i covers frame pixel edges [i/s, (i+1)/s).
    Rows sum to 1 (over the part of the event pixel inside the frame)."""
    s = float(event_scale)
    overlap = axis_overlaps(np.arange(n_event, dtype=np.float64) / s, 1.0 / s, n_frame)
    return overlap / np.maximum(overlap.sum(axis=1, keepdims=True), 1e-12)


def axis_overlaps(low: np.ndarray, extent: float, n_frame: int) -> np.ndarray:
    """(n, n_frame) lengths, in frame pixels, of each event pixel's overlap with each frame pixel
    along one axis, for event pixel i covering frame pixel edges [low[i], low[i] + extent) (frame
    pixel j covers [j, j + 1)). Overlaps under ``SLIVER_PX`` (rounding where edges coincide) count
    as none."""
    lo = np.asarray(low, dtype=np.float64)[:, None]
    edges = np.arange(n_frame, dtype=np.float64)[None, :]
    overlap = np.minimum(lo + extent, edges + 1.0) - np.maximum(lo, edges)
    return np.where(overlap > SLIVER_PX, overlap, 0.0)


def nonzero_band(weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The nonzero band of each row of an ``area_weights`` matrix: (n, B) columns and weights, in
    column order (weight 0 on the padding of shorter rows)."""
    nonzero = weights > 0
    first = nonzero.argmax(axis=1)
    width = int(nonzero.sum(axis=1).max())
    columns = np.minimum(first[:, None] + np.arange(width), weights.shape[1] - 1)
    return columns, np.take_along_axis(weights, columns, axis=1) * (columns == first[:, None] + np.arange(width))


def footprints(event_shape: tuple[int, int], frame_shape: tuple[int, int], event_scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Frame pixels under each event pixel of the grid ``psfmt.scale_affine(event_scale)``: (He·We, K)
    flat frame indices v·W + u and (He·We, K) area weights (0 on padding slots)."""
    (he, we), (h, w) = event_shape, frame_shape
    return _separable(area_weights(he, h, event_scale), area_weights(we, w, event_scale), w)


def affine_footprints(affine: np.ndarray, event_shape: tuple[int, int], frame_shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Frame pixels under each event pixel through a calibrated (2, 3) event→frame ``affine``, which
    maps event pixel centres to frame pixel coordinates (both with centres at integers): (He·We, K)
    flat frame indices v·W + u and (He·We, K) shares of the event pixel's area in each (0 on padding
    slots). The shares of an event pixel sum to the part of it inside the frame: 1 wholly inside,
    less at the frame's edge, 0 outside.

    Exact for an axis-aligned affine (any scale and offset per axis, mirrored or not, as calibrated
    rigs give): products of ``axis_overlaps``. An affine that rotates or shears maps a pixel to a
    parallelogram, whose shares are counted on ``FOOTPRINT_SAMPLES_PER_PX`` samples a frame pixel a
    side.

    Raises
    ------
    UserError
        An event pixel wider than ``MAX_FOOTPRINT_EXTENT_PX`` frame pixels along a frame axis.
    """
    a = np.asarray(affine, dtype=np.float64)
    (he, we), (h, w) = event_shape, frame_shape
    check_footprint_extent(a, "event→frame affine")
    if a[0, 1] == 0.0 and a[1, 0] == 0.0 and a[0, 0] != 0.0 and a[1, 1] != 0.0:
        rows, cols = (
            axis_overlaps(a[i, i] * np.arange(n, dtype=np.float64) + a[i, 2] + 0.5 - abs(a[i, i]) / 2, abs(a[i, i]), size) / abs(a[i, i])
            for i, n, size in ((1, he, h), (0, we, w))
        )
        return _separable(rows, cols, w)
    return _sampled_footprints(a, event_shape, frame_shape)


def check_footprint_extent(affine: np.ndarray, where: str) -> None:
    """UserError ``{where}: …`` when the (2, 3) event→frame ``affine`` makes an event pixel wider than
    ``MAX_FOOTPRINT_EXTENT_PX`` frame pixels along a frame axis (or is not finite)."""
    extent = float(np.abs(np.asarray(affine, dtype=np.float64)[:, :2]).sum(axis=1).max())
    if not extent <= MAX_FOOTPRINT_EXTENT_PX:
        raise UserError(f"{where}: an event pixel spans {extent:.3g} frame pixels along an axis (at most {MAX_FOOTPRINT_EXTENT_PX:g})")


def _separable(rows: np.ndarray, cols: np.ndarray, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Footprints (flat frame indices, weights) of the event grid whose rows and columns weigh the
    frame's by the matrices ``rows`` (He, H) and ``cols`` (We, W), each row a contiguous band."""
    (r_idx, r_w), (c_idx, c_w) = nonzero_band(rows), nonzero_band(cols)
    he, we = len(r_idx), len(c_idx)
    frame = (r_idx[:, None, :, None] * width + c_idx[None, :, None, :]).reshape(he * we, -1)
    weight = (r_w[:, None, :, None] * c_w[None, :, None, :]).reshape(he * we, -1)
    return frame, weight


def _sampled_footprints(affine: np.ndarray, event_shape: tuple[int, int], frame_shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """``affine_footprints`` of any affine: n×n samples per event pixel, n enough for
    ``FOOTPRINT_SAMPLES_PER_PX`` a frame pixel, each counted in the frame pixel it falls in; event
    pixels in blocks of bounded size (a sample table of about ``FOOTPRINT_BLOCK_SAMPLES``)."""
    (he, we), (h, w) = event_shape, frame_shape
    # (the frame pixels an event pixel's side crosses, less a hair so that 2.0000001 is 2)
    n = max(2, int(np.ceil(FOOTPRINT_SAMPLES_PER_PX * np.abs(affine[:, :2]).sum(axis=0).max() - 1e-6)))
    offsets = (np.arange(n) + 0.5) / n - 0.5
    du, dv = (x.ravel() for x in np.meshgrid(offsets, offsets))
    block = max(1, FOOTPRINT_BLOCK_SAMPLES // (n * n))
    parts: list[tuple[np.ndarray, np.ndarray]] = []
    for start in range(0, he * we, block):
        ve, ue = np.divmod(np.arange(start, min(start + block, he * we)), we)
        su, sv = ue[:, None] + du, ve[:, None] + dv
        fu = np.floor(affine[0, 0] * su + affine[0, 1] * sv + affine[0, 2] + 0.5)
        fv = np.floor(affine[1, 0] * su + affine[1, 1] * sv + affine[1, 2] + 0.5)
        inside = (fu >= 0) & (fu < w) & (fv >= 0) & (fv < h)
        flat = np.sort(np.where(inside, fv * w + fu, -1.0).astype(np.int64), axis=1)
        valid = flat >= 0
        first = valid & np.concatenate([np.ones((len(flat), 1), bool), flat[:, 1:] != flat[:, :-1]], axis=1)
        slot = np.cumsum(first, axis=1) - 1
        slots = max(1, int(first.sum(axis=1).max()))
        row = np.broadcast_to(np.arange(len(flat))[:, None], flat.shape)
        index = np.zeros((len(flat), slots), np.int64)
        index[row[first], slot[first]] = flat[first]
        count = np.zeros((len(flat), slots))
        np.add.at(count, (row[valid], slot[valid]), 1.0)
        parts.append((index, count / (n * n)))
    slots = max(index.shape[1] for index, _ in parts)
    frame = np.concatenate([np.pad(index, ((0, 0), (0, slots - index.shape[1]))) for index, _ in parts])
    weight = np.concatenate([np.pad(share, ((0, 0), (0, slots - share.shape[1]))) for _, share in parts])
    return frame, weight


def frame_to_event(affine: np.ndarray, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Event-grid coordinates (u_e, v_e) of frame coordinates (u, v) through the inverse of the
    (2, 3) event→frame ``affine``."""
    a = np.asarray(affine, dtype=np.float64)
    ue, ve = np.linalg.solve(a[:, :2], np.stack([np.ravel(u) - a[0, 2], np.ravel(v) - a[1, 2]]))
    return ue.reshape(np.shape(u)), ve.reshape(np.shape(v))


def nearest_super_pixel(affine: np.ndarray, height: int, width: int, event_height: int, event_width: int) -> np.ndarray:
    """(H·W,) flat event pixel whose centre is nearest each frame pixel (clipped to the sensor)."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    ue, ve = frame_to_event(affine, u, v)
    ue = np.clip(np.rint(ue), 0, event_width - 1).astype(np.int64)
    ve = np.clip(np.rint(ve), 0, event_height - 1).astype(np.int64)
    return (ve * event_width + ue).ravel()


def bilinear_taps(u: np.ndarray, v: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear interpolation on a height×width grid at (u, v) (grid pixel centres at integers, clamped
    to the grid): (P, 4) flat grid indices and (P, 4) weights."""
    u = np.clip(u, 0.0, width - 1.0)
    v = np.clip(v, 0.0, height - 1.0)
    u0 = np.minimum(np.floor(u).astype(np.int64), max(width - 2, 0))
    v0 = np.minimum(np.floor(v).astype(np.int64), max(height - 2, 0))
    u1, v1 = np.minimum(u0 + 1, width - 1), np.minimum(v0 + 1, height - 1)
    fu, fv = u - u0, v - v0
    index = np.stack([v0 * width + u0, v0 * width + u1, v1 * width + u0, v1 * width + u1], axis=1)
    weight = np.stack([(1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv], axis=1)
    return index, weight


def to_frames(values: np.ndarray, known: np.ndarray, affine: np.ndarray, height: int, width: int,
              event_height: int, event_width: int) -> tuple[np.ndarray, np.ndarray]:
    """Event-grid values bilinearly interpolated to every frame pixel from the known ones among its
    four neighbouring super pixels (weights renormalised).

    Parameters
    ----------
    values
        (He·We, C) values on the event grid, flat index v_e·We + u_e.
    known
        (He·We,) bool, where ``values`` are known.
    affine
        (2, 3) event→frame affine.
    height, width
        Frame size H, W, pixels.
    event_height, event_width
        Event grid size He, We, pixels.

    Returns
    -------
    values : numpy.ndarray
        (H·W, C) interpolated values, flat index v·W + u; 0 where no neighbour was known.
    any_known : numpy.ndarray
        (H·W,) bool, where any of the four neighbours was known.
    """
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    ue, ve = frame_to_event(affine, u.ravel(), v.ravel())
    index, weight = bilinear_taps(ue, ve, event_width, event_height)
    weight = weight * known[index]
    total = weight.sum(axis=1)
    out = np.einsum("pk,pkc->pc", weight, values[index]) / np.where(total > 0, total, 1.0)[:, None]
    return out, total > 0
