"""Cast-shadow intervals from the event interval profile: Algorithm 1 of the DualResPS supplement
(``spikes``, the paper's detector).

A spike f > θ is a shadow exit, f < −θ an entry. Pass ρ = +1 takes every exit spike as an anchor,
searches backwards (within the max duration D, cyclically over the period) for the farthest entry
whose |f| exceeds a threshold θ' that starts at θ and decays by γ (the last step clamped to θ_min)
while none is found (an entry softened by attached shadow is a weak spike), then forwards from that
entry for the farthest strong exit (|f| > θ) within D: the shadow is [entry, exit]. Pass ρ = −1 does
the mirror image from entry anchors not inside a shadow found already. Every anchor of a pass is
searched at once with array operations over (anchor, candidate offset) blocks; only the threshold
decay loops.

A refractory period R caps |f| = C/Δt at C/R: θ is lowered to ``SPIKE_SHARE`` of that cap, and
where even that falls below ``SPIKE_FLOOR_PER_S`` ordinary shading reaches it, an edge fires a single
event instead of a burst, and the detector finds nothing (the ``silences`` detector is made for
such sensors).
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from pstoolkit.plugin.options import Option
from pstoolkit.shadows.base import ShadowDetector, ShadowEvidence, ShadowMask
from pstoolkit.shadows.intervals import ShadowIntervals, ShadowTable
from pstoolkit.shadows.period_profile import Profile

SPIKE_SHARE = 2.0 / 3.0
SPIKE_FLOOR_PER_S = 300.0

# Anchors searched per block, so one block's (anchor, offset) arrays hold about this many values.
BLOCK_VALUES = 1 << 22


def _farthest(profile: Profile, anchors: np.ndarray, direction: int, sign: int, threshold: float, max_us: float) -> np.ndarray:
    """For each anchor, the sample of the same pixel farthest from it in ``direction`` (+1 later,
    −1 earlier, cyclic gap in (0, max_us)) with sign·f > threshold; −1 where there is none."""
    out = np.full(len(anchors), -1, dtype=np.int64)
    if len(anchors) == 0:
        return out
    period = profile.period_us
    widest = int(profile.count[anchors].max())
    offsets = np.arange(1, widest, dtype=np.int64)
    if offsets.size == 0:
        return out
    step = max(1, BLOCK_VALUES // offsets.size)
    for start in range(0, len(anchors), step):
        a = anchors[start : start + step]
        local = (a - profile.first[a])[:, None]
        count = profile.count[a][:, None]
        candidate = profile.first[a][:, None] + np.mod(local + direction * offsets[None, :], count)
        gap = np.mod(direction * (profile.t_us[candidate] - profile.t_us[a][:, None]), period)
        ok = (offsets[None, :] < count) & (gap > 0) & (gap < max_us) & (sign * profile.f[candidate] > threshold)
        # gaps grow with the offset within a pixel, so the farthest valid one is the last valid one
        last = ok.shape[1] - 1 - np.argmax(ok[:, ::-1], axis=1)
        found = ok.any(axis=1)
        out[start : start + step] = np.where(found, candidate[np.arange(len(a)), last], -1)
    return out


def find_shadows(
    profile: Profile,
    *,
    theta: float,
    theta_min: float,
    gamma: float,
    max_duration_us: float,
) -> ShadowIntervals:
    """Algorithm 1 (FINDSHADOWBOUNDARIES) at every super pixel of ``profile``; thresholds in log units
    per second, ``gamma`` in (0, 1) the decay factor, ``max_duration_us`` the longest shadow D."""
    pixels, starts, ends = [], [], []
    covered = np.zeros(len(profile), dtype=bool)
    for rho in (1, -1):
        anchors = np.flatnonzero((rho * profile.f > theta) & ~covered)
        opposite = np.full(len(anchors), -1, dtype=np.int64)
        level = theta
        while True:
            todo = np.flatnonzero(opposite < 0)
            if todo.size == 0:
                break
            # ρ = +1: entries (f < −θ') before the exit anchor; ρ = −1: exits (f > θ') after the entry
            opposite[todo] = _farthest(profile, anchors[todo], -rho, -rho, level, max_duration_us)
            if level <= theta_min:
                break
            level = max(level * gamma, theta_min)
        keep = opposite >= 0
        anchors, opposite = anchors[keep], opposite[keep]
        confirm = _farthest(profile, opposite, rho, rho, theta, max_duration_us)
        keep = confirm >= 0
        opposite, confirm = opposite[keep], confirm[keep]
        lo, hi = (opposite, confirm) if rho > 0 else (confirm, opposite)
        pixels.append(profile.pixel[lo])
        starts.append(profile.t_us[lo])
        ends.append(profile.t_us[hi])
        covered |= _covered(profile, lo, hi)
    # anchors of one shadow (every event of its exit burst) find the same interval: keep one
    found = np.unique(np.stack([np.concatenate(pixels), np.concatenate(starts), np.concatenate(ends)], axis=1), axis=0)
    return ShadowIntervals(found[:, 0].astype(np.int64), found[:, 1], found[:, 2])


def _covered(profile: Profile, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Samples lying within one of the intervals [lo, hi] (sample indices, cyclic within a pixel)."""
    table = ShadowTable.build(ShadowIntervals(profile.pixel[lo], profile.t_us[lo], profile.t_us[hi]), profile.period_us)
    return table.contains(profile.pixel, profile.t_us)




def spike_threshold(theta_per_s: float, contrast: float, refractory_us: float) -> float:
    """θ (log units per second) lowered to ``SPIKE_SHARE`` of the cap C/R a refractory period R puts
    on |f| = C/Δt: what counts as an abrupt change."""
    cap = contrast / (refractory_us * 1e-6) if refractory_us > 0 else np.inf
    return float(min(theta_per_s, SPIKE_SHARE * cap))


class SpikeDetector(ShadowDetector):
    name: ClassVar[str] = "spikes"
    summary: ClassVar[str] = "Algorithm 1 of DualResPS: matched entry/exit spikes of the event interval profile (short refractory periods)"
    options: ClassVar[tuple[Option, ...]] = (
        Option("theta_per_s", float, 4000.0, "θ, the spike that starts a search, log units per second", minimum=1.0),
        Option("theta_min_per_s", float, 500.0, "θ_min, the lowest decayed threshold for a softened edge", minimum=1.0),
        Option("gamma", float, 0.7, "γ, the threshold decay factor", minimum=0.01, maximum=0.99),
        Option("max_shadow_share", float, 0.5, "D, the longest shadow as a share of the light period", minimum=0.01, maximum=0.99),
    )

    def detect(self, evidence: ShadowEvidence, options: dict[str, Any]) -> ShadowMask:
        contrast = min(evidence.contrast_pos, evidence.contrast_neg)
        theta = spike_threshold(options["theta_per_s"], contrast, evidence.refractory_us)
        if theta < SPIKE_FLOOR_PER_S:
            return evidence.no_mask()
        found = find_shadows(
            evidence.profile, theta=theta, theta_min=min(options["theta_min_per_s"], theta), gamma=options["gamma"],
            max_duration_us=options["max_shadow_share"] * evidence.period_us,
        )
        return evidence.event_mask(found)
