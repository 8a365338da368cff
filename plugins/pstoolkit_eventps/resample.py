"""Normal maps from the event sensor's grid to the capture's target grid."""

from __future__ import annotations

import cv2
import numpy as np

import psfmt


def event_to_frame_affine(capture: psfmt.Capture, target: tuple[int, int]) -> np.ndarray:
    """The 2×3 affine from event pixel centres to target pixel coordinates: the calibrated one, or
    ``psfmt.scale_affine`` for an event sensor that sees the target's field of view."""
    events = capture.events
    assert events is not None
    if capture.calibration.event_to_frame is not None:
        return capture.calibration.event_to_frame
    return psfmt.scale_affine(events.width / target[1])


def to_target(normal: np.ndarray, mask: np.ndarray, affine: np.ndarray, target: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Resample event-grid normals (..., He, We, 3) and mask (..., He, We) to ``target`` (H, W):
    each target pixel is mapped back through the inverse affine and the masked normals are
    interpolated bilinearly and renormalised; a target pixel is in the mask when the bilinear
    share of masked event pixels is at least one half."""
    h, w = target
    he, we = mask.shape[-2:]
    if (he, we) == (h, w) and np.allclose(affine, np.eye(2, 3)):
        return normal, mask
    inverse = np.linalg.inv(affine[:, :2])
    u = (np.arange(w, dtype=np.float64) - affine[0, 2])[None, :]
    v = (np.arange(h, dtype=np.float64) - affine[1, 2])[:, None]
    map_u = (inverse[0, 0] * u + inverse[0, 1] * v).astype(np.float32)
    map_v = (inverse[1, 0] * u + inverse[1, 1] * v).astype(np.float32)
    flat_normal = normal.reshape(-1, he, we, 3)
    flat_mask = mask.reshape(-1, he, we)
    out_normal = np.zeros((len(flat_mask), h, w, 3), dtype=np.float32)
    out_mask = np.zeros((len(flat_mask), h, w), dtype=bool)
    for i in range(len(flat_mask)):
        weight = flat_mask[i].astype(np.float32)
        source = np.concatenate([flat_normal[i] * weight[..., None], weight[..., None]], axis=-1).astype(np.float32)
        sampled = cv2.remap(source, map_u, map_v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        vector = sampled[..., :3]
        length = np.sqrt(np.einsum("hwc,hwc->hw", vector, vector))
        inside = (sampled[..., 3] >= 0.5) & (length > 0)
        np.divide(vector, length[..., None], out=out_normal[i], where=inside[..., None])
        out_mask[i] = inside
    return out_normal.reshape(normal.shape[:-3] + (h, w, 3)), out_mask.reshape(mask.shape[:-2] + (h, w))
