"""Cast shadows the events see by their edges, however much light fills them (``fused``'s second
confirmation).

Inter-reflected light fills the cast shadows of a concavity, so the events there do not fall silent and
a dark span (``silences``) confirms too few of them: on path-traced `hollows` ``fused`` kept under half
of what its own surface predicted. The edges still show: entering the shadow takes the direct light at
once and leaving gives it back, so across the entry the super pixel's events fall and across the exit
they rise. A super pixel's predicted shadow — where its shadowed share of the surface is at least
``edge_tracking.SHARE_THRESHOLD``, the edges the height calibration scores — is *seen* when, within the
tolerance of its entry, more of the super pixel's events fall than rise, and within that of its exit
more rise than fall. A net count rather than an onset: the events of noise come in both polarities and
mostly cancel, the step of a shadow's edge does not.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from pstoolkit.shadows.base import ShadowEvidence
from pstoolkit.shadows.edge_tracking import EdgeTracker, SuperPixels
from pstoolkit.shadows.height_scale import period_keys, super_pixel_edges, within
from pstoolkit.shadows.intervals import ShadowIntervals, rasterize

if TYPE_CHECKING:
    from pstoolkit.shadows.device_tracking import DeviceEdgeTracker


@dataclass(frozen=True)
class SeenShadows:
    """The predicted shadows of super pixels whose edges the events see: ``columns`` (C,) the event
    pixels with at least one, ``seen`` (steps, C) bool when each is in one on the time grid
    (``intervals.grid_times``); ``pixel_share`` (P,) the share of the period the surface shadows each
    masked frame pixel (flat order); ``runs`` and ``confirmed`` the predicted shadows and those seen."""

    columns: np.ndarray
    seen: np.ndarray
    pixel_share: np.ndarray
    runs: int
    confirmed: int

    def record(self) -> dict[str, int]:
        return {"edge_runs": self.runs, "edge_seen": self.confirmed}


def seen_shadows(evidence: ShadowEvidence, height: np.ndarray, time_steps: int, margin_px: float, tolerance_deg: float
                 ) -> SeenShadows:
    """The shadows of the surface of ``height`` (pixels) whose edges the events of ``evidence`` see
    (module docstring), marched at ``time_steps`` light directions per period with the occluder margin
    ``margin_px`` (``surface_sweep.surface_shadow_blocks``); ``seen_edges`` on its ``EdgeTracker``."""
    tracker = super_pixel_edges(evidence, SuperPixels.shared(evidence), height, time_steps, margin_px, count_pixels=True)
    return seen_edges(evidence, tracker, tolerance_deg)


def seen_edges(evidence: ShadowEvidence, tracker: EdgeTracker | DeviceEdgeTracker, tolerance_deg: float) -> SeenShadows:
    """The predicted shadows of ``tracker`` (fed a whole period, counting its pixels' bins) whose edges
    the events of ``evidence`` see.

    Parameters
    ----------
    evidence
        The capture's evidence (its events' ``profile``, super pixels, period).
    tracker
        The super pixels' shadow edges on the time grid of its ``steps`` bins per period, made with
        ``count_pixels``.
    tolerance_deg
        How far, in degrees of the turn, the events that show an edge may lie from the predicted one.

    Returns
    -------
    SeenShadows
        The seen shadows on the time grid, for the event pixels that have any.
    """
    period, time_steps = evidence.period_us, tracker.steps
    bins, pixel, entering = tracker.edges()
    if tracker.pixel_bins is None:
        raise ValueError("seen_edges needs an EdgeTracker made with count_pixels")
    pixel_share = tracker.pixel_bins / float(max(time_steps, 1))
    if bins.size == 0:
        return SeenShadows(np.empty(0, dtype=np.int64), np.zeros((time_steps, 0), dtype=bool), pixel_share, 0, 0)
    # a super pixel's edges alternate in time: each entry's exit is the super pixel's next edge, cyclically
    order = np.lexsort((bins, pixel))
    bins, pixel, entering = bins[order], pixel[order], entering[order]
    starts = np.r_[0, np.flatnonzero(np.diff(pixel)) + 1]
    following = np.arange(1, bins.size + 1)
    following[np.r_[starts[1:], bins.size] - 1] = starts
    step_us = period / time_steps
    entry_us, exit_us, owner = bins[entering] * step_us, bins[following[entering]] * step_us, pixel[entering]
    falling, rising = period_keys(evidence.profile)
    tolerance_us = tolerance_deg / 360.0 * period

    def net(toward: np.ndarray, against: np.ndarray, phase_us: np.ndarray) -> np.ndarray:
        return (within(toward, owner, phase_us, period, tolerance_us)
                - within(against, owner, phase_us, period, tolerance_us))

    seen = (net(falling, rising, entry_us) > 0) & (net(rising, falling, exit_us) > 0)
    columns, column = np.unique(owner[seen], return_inverse=True)
    grid = rasterize(ShadowIntervals(column, entry_us[seen], exit_us[seen]), columns.size, period, time_steps)
    return SeenShadows(columns, grid, pixel_share, int(owner.size), int(np.count_nonzero(seen)))
