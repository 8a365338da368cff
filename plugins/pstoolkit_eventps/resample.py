"""Normal maps from the event sensor's grid to the capture's target grid."""

from __future__ import annotations

import cv2
import numpy as np

import psfmt
from pstoolkit.grid import default_affine


def event_to_frame_affine(capture: psfmt.Capture, target: tuple[int, int]) -> np.ndarray:
    """The 2×3 affine from event pixel centres to target pixel coordinates: the calibrated one, or
    ``pstoolkit.grid.default_affine``: an event sensor that sees the target's field of view."""
    events = capture.events
    assert events is not None
    if capture.calibration.event_to_frame is not None:
        return capture.calibration.event_to_frame
    return default_affine(events.width, target[1])


class Resampler:
    """Event-grid maps of shape ``event_shape`` (He, We) to ``target`` (H, W): each target pixel is
    mapped back through the inverse of the event→target ``affine``; the maps are computed once."""

    def __init__(self, affine: np.ndarray, event_shape: tuple[int, int], target: tuple[int, int]) -> None:
        self.target = target
        self.identity = event_shape == target and np.allclose(affine, np.eye(2, 3))
        h, w = target
        inverse = np.linalg.inv(affine[:, :2])
        u = (np.arange(w, dtype=np.float64) - affine[0, 2])[None, :]
        v = (np.arange(h, dtype=np.float64) - affine[1, 2])[:, None]
        self.map_u = (inverse[0, 0] * u + inverse[0, 1] * v).astype(np.float32)
        self.map_v = (inverse[1, 0] * u + inverse[1, 1] * v).astype(np.float32)
        self.covered = self._remap(np.ones(event_shape, np.float32), cv2.INTER_LINEAR) >= 0.5
        """Target pixels whose bilinear share of the sensor's pixels is at least one half."""

    def _remap(self, image: np.ndarray, interpolation: int) -> np.ndarray:
        return cv2.remap(image, self.map_u, self.map_v, interpolation, borderMode=cv2.BORDER_CONSTANT, borderValue=0)

    def normals(self, normal: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Normals (He, We, 3) and mask (He, We) at the target: the masked normals interpolated
        bilinearly and renormalised; a target pixel is in the mask when the bilinear share of masked
        event pixels is at least one half, and its normal is zero outside it."""
        if self.identity:
            return normal, mask
        if mask.all():
            vector, inside = self._remap(np.asarray(normal, np.float32), cv2.INTER_LINEAR), self.covered.copy()
        else:
            weight = mask.astype(np.float32)
            source = np.concatenate([normal * weight[..., None], weight[..., None]], axis=-1).astype(np.float32)
            sampled = self._remap(source, cv2.INTER_LINEAR)
            vector, inside = np.ascontiguousarray(sampled[..., :3]), sampled[..., 3] >= 0.5
        length = np.sqrt(np.einsum("hwc,hwc->hw", vector, vector))
        inside &= length > 0
        vector *= (np.where(inside, 1.0, 0.0) / np.where(inside, length, 1.0)).astype(np.float32)[..., None]
        return vector, inside

    def nearest(self, values: np.ndarray) -> np.ndarray:
        """An event-grid map (He, We) float32 at the target: each target pixel takes the event pixel its
        centre maps back to (0 outside the sensor), so levels such as a confidence stay levels."""
        return values if self.identity else self._remap(values, cv2.INTER_NEAREST)
