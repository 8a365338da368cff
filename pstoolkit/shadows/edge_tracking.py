"""The edges of the super pixels' shadows on the surface's swept shadows: where a super pixel's
shadowed share of its frame pixels crosses ``SHARE_THRESHOLD`` (``EdgeTracker``), fed the sweep's
blocks in time order. The height calibration (``height_scale``) scores them against the events'
onsets, ``fused`` (``edge_seen``) looks for the events' fall and rise at them; on a device,
``device_tracking.DeviceEdgeTracker`` tracks them there."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pstoolkit.shadows.base import ShadowEvidence
from pstoolkit.shadows.sweep_kernels import reached

# Share of a super pixel's frame pixels in shadow at which its events see the edge: an edge that
# takes most of the direct light drops the super pixel's mean by one contrast threshold about there.
SHARE_THRESHOLD = 0.3

@dataclass(frozen=True)
class SuperPixels:
    """The super pixels covering the masked frame pixels: ``used`` (G,) the event pixels, increasing;
    ``group`` (P,) int32 the position in ``used`` of each masked frame pixel's (flat order); ``needed``
    (G,) int32 how many of a super pixel's frame pixels make the ``SHARE_THRESHOLD`` share. ``there``:
    their copies on torch devices, by device (``device_tracking``)."""

    used: np.ndarray
    group: np.ndarray
    needed: np.ndarray
    there: dict[str, Any] = field(default_factory=dict, repr=False, compare=False)

    @classmethod
    def shared(cls, evidence: ShadowEvidence) -> SuperPixels:
        """``of`` the evidence, made once for it and its copies (``ShadowEvidence.of_capture``): every
        sweep of every detection tracks them."""
        return evidence.of_capture("super_pixels", lambda: cls.of(evidence))

    @classmethod
    def of(cls, evidence: ShadowEvidence) -> SuperPixels:
        """Those of the evidence's ``super_pixel`` and ``mask``."""
        covering = evidence.super_pixel[np.flatnonzero(np.asarray(evidence.mask).ravel())]
        used, group, count = np.unique(covering, return_inverse=True, return_counts=True)
        # a whole count s reaches the share x = threshold·count exactly when it reaches ceil(x)
        return cls(used, group.astype(np.int32), np.ceil(SHARE_THRESHOLD * count).astype(np.int32))


class EdgeTracker:
    """The edges of the super pixels' shadows, fed the surface's shadow blocks (``surface_sweep.
    surface_shadow_blocks``) in time order: where a super pixel's shadowed share of ``groups`` crosses
    ``SHARE_THRESHOLD``. With ``count_pixels``, also counts the time bins each masked frame pixel is
    shadowed (``pixel_bins``). Holds a byte per super pixel and direction of a block besides its edges."""

    def __init__(self, groups: SuperPixels, *, count_pixels: bool = False) -> None:
        self.groups = groups
        self.pixel_bins = np.zeros(groups.group.size, dtype=np.int32) if count_pixels else None
        self._bins: list[np.ndarray] = []
        self._pixel: list[np.ndarray] = []
        self._entering: list[np.ndarray] = []
        self._first: np.ndarray | None = None
        self._last: np.ndarray | None = None
        self.steps = 0

    def feed(self, block: np.ndarray) -> None:
        """The next (n, P) bool rows of the surface's shadows."""
        groups = self.groups
        if self.pixel_bins is not None:
            self.pixel_bins += np.count_nonzero(block, axis=0).astype(np.int32)
        state = np.empty((len(block), groups.used.size), dtype=bool)
        reached(np.ascontiguousarray(block).view(np.uint8), groups.group, groups.needed, state)
        if self._first is None:
            self._first = state[0]
        before = np.vstack([state[:1] if self._last is None else self._last[None], state[:-1]])
        change = state != before
        # few super pixels change within a block: np.nonzero over the whole block took longer than the sweep
        changing = np.flatnonzero(change.any(axis=0))
        k, e = np.nonzero(change[:, changing])
        e = changing[e]
        self._bins.append(self.steps + k)
        self._pixel.append(groups.used[e])
        self._entering.append(state[k, e])
        self._last = state[-1]
        self.steps += len(block)

    def edges(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every edge over the period as (time bin where the new state starts, super pixel, entering),
        in time order, the period's wrap included."""
        if self._first is None:
            empty = np.empty(0, dtype=np.int64)
            return empty, empty, np.empty(0, dtype=bool)
        # the period wraps: the first bin follows the last
        wrap = np.flatnonzero(self._first != self._last)
        bins = np.concatenate([np.zeros(wrap.size, dtype=np.int64), *self._bins])
        pixel = np.concatenate([self.groups.used[wrap], *self._pixel])
        entering = np.concatenate([self._first[wrap], *self._entering])
        return bins, pixel, entering

