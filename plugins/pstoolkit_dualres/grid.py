"""Geometry between the frame grid and the event grid (super pixels): the calibrated event→frame
affine inverted, nearest and bilinear lookups of event-grid values at frame pixels."""

from __future__ import annotations

import numpy as np


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
    """Event-grid ``values`` (He·We, C) known at ``known`` (He·We,) bilinearly interpolated to every
    frame pixel from the known ones among its four neighbouring super pixels (weights renormalised):
    (H·W, C) values and (H·W,) bool where any neighbour was known."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    ue, ve = frame_to_event(affine, u.ravel(), v.ravel())
    index, weight = bilinear_taps(ue, ve, event_width, event_height)
    weight = weight * known[index]
    total = weight.sum(axis=1)
    out = np.einsum("pk,pkc->pc", weight, values[index]) / np.where(total > 0, total, 1.0)[:, None]
    return out, total > 0
