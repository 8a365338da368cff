"""The ``quiet`` shadow detector: an event pixel that falls silent for longer than a threshold between
a darkening event and a brightening one, and for several times longer than the event intervals
around that silence, is taken to be in a cast shadow over it (a pixel in the dark sees no change and
the light comes back at the shadow's exit, whereas smooth shading slows its events down gradually;
a mask that calls lit time dark costs far more accuracy than a missed shadow).

A detector receives ``pstoolkit.shadows.ShadowEvidence`` — here its ``profile``, the events of one
light period grouped by event pixel, each with its phase ``t_us`` in [0, period) — and returns a
``ShadowMask``; ``evidence.event_mask`` turns intervals found at event pixels into one, each frame
pixel taking those of the event pixel covering it.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from pstoolkit import Option, ShadowDetector, ShadowEvidence, ShadowIntervals, ShadowMask


class QuietDetector(ShadowDetector):
    name: ClassVar[str] = "quiet"
    summary: ClassVar[str] = "event pixels silent between a darkening and a brightening event are in shadow meanwhile"
    options: ClassVar[tuple[Option, ...]] = (
        Option("silence_ms", float, 3.0, "shortest silence taken as a shadow, ms", minimum=0.0),
        Option("ratio", float, 3.0, "a silence must last this many times the intervals beside it", minimum=1.0),
    )

    def detect(self, evidence: ShadowEvidence, options: dict[str, Any]) -> ShadowMask:
        profile = evidence.profile
        k = np.arange(len(profile))
        # each event's neighbours in its pixel, cyclically over the period
        before, earlier, after = profile.neighbour(k, -1), profile.neighbour(k, -2), profile.neighbour(k, 1)
        period = evidence.period_us
        gap = np.mod(profile.t_us - profile.t_us[before], period)
        beside = np.maximum(np.mod(profile.t_us[before] - profile.t_us[earlier], period), np.mod(profile.t_us[after] - profile.t_us, period))
        quiet = (profile.count > 2) & (profile.p[before] < 0) & (profile.p > 0)
        quiet &= (gap > 1000.0 * options["silence_ms"]) & (gap > options["ratio"] * beside)
        return evidence.event_mask(ShadowIntervals(profile.pixel[quiet], profile.t_us[before[quiet]], profile.t_us[quiet]))
