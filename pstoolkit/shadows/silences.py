"""Cast shadows from the events' polarity pattern, for sensors whose refractory period hides the
bursts Algorithm 1 looks for (``silences``).

A cast shadow drops a pixel's irradiance to almost nothing and brings it back at its exit. Whatever
the refractory rule (``pstoolkit.events.rule``), the events of one turn then show a run of falling
(negative) events ending the lit time and a rising (positive) event at the exit:

- reset-at-end: the edge fires one negative event, the pixel resets to the dark level after R and
  stays silent until the exit fires a positive event;
- rate-limited: the reference falls by one threshold per event, so the pixel keeps firing negative
  events every R while in shadow, then positive ones every R after the exit;
- R = 0 (ESIM's rule): a burst of negative events at the entry, silence, a burst of positive ones.

A dark span is therefore [the first event of the tail of a negative run whose events follow each
other within R + ``tolerance_us`` (the run's last event when there is no such tail), the positive
event after it], when it lasts longer than ``min_gap_us``. Smooth shading makes such spans too (a
pixel turning away from the light and back), so on its own the detector also asks the span to be
longer than ``ratio`` times the intervals on either side of it (a smooth minimum slows the events
gradually); the ``fused`` detector instead lets the surface decide where a span is a shadow.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from pstoolkit.plugin.options import Option
from pstoolkit.shadows.base import ShadowDetector, ShadowEvidence, ShadowMask
from pstoolkit.shadows.intervals import ShadowIntervals
from pstoolkit.shadows.period_profile import Profile

# Slack (µs) on "one refractory period apart" for events of a rate-limited run: the timestamps'
# resolution and the sensor's own jitter.
RUN_TOLERANCE_US = 2.0


def dark_spans(
    profile: Profile,
    *,
    refractory_us: float,
    min_gap_us: float,
    ratio: float = 0.0,
    tolerance_us: float = RUN_TOLERANCE_US,
    max_share: float = 0.6,
) -> ShadowIntervals:
    """Dark spans (see the module docstring) of every event pixel of ``profile``.

    Parameters
    ----------
    profile
        The events of one light period, grouped by event pixel (``interval_profile``).
    refractory_us
        The sensor's refractory period R, µs.
    min_gap_us
        Shortest span kept, µs (exclusive).
    ratio
        When > 0, keeps only spans longer than ``ratio`` times the event intervals just before and after
        them (0: off).
    tolerance_us
        Slack on "one refractory period apart" for the events of a negative run, µs.
    max_share
        Drops spans as long as this share of the period or longer.

    Returns
    -------
    ShadowIntervals
        Phase intervals, µs, at flat event pixels: from the start of the run to the positive event.
    """
    n = len(profile)
    if n == 0:
        return ShadowIntervals.empty()
    period = profile.period_us
    k = np.arange(n)
    prev, gap = profile.previous()
    # an event continues a run when it and its predecessor are negative and one refractory period apart
    runs_on = (profile.p < 0) & (profile.p[prev] < 0) & (gap <= refractory_us + tolerance_us) & (profile.count > 1)
    local = k - profile.first
    # the start of the run each event belongs to: the latest event at or before it (within its
    # pixel, not wrapping) that does not continue a run
    start = np.where(runs_on & (local > 0), -1, k)
    start = np.maximum.accumulate(start)
    start = np.maximum(start, profile.first)
    ends = np.flatnonzero((profile.p > 0) & (profile.p[prev] < 0) & (profile.count > 1))
    last_negative = prev[ends]
    begin = start[last_negative]
    span = np.mod(profile.t_us[ends] - profile.t_us[begin], period)
    keep = (span > min_gap_us) & (span < max_share * period)
    if ratio > 0:
        before = np.mod(profile.t_us[begin] - profile.t_us[profile.neighbour(begin, -1)], period)
        after = np.mod(profile.t_us[profile.neighbour(ends, 1)] - profile.t_us[ends], period)
        keep &= span > ratio * np.maximum(before, after)
    return ShadowIntervals(profile.pixel[ends[keep]], profile.t_us[begin[keep]], profile.t_us[ends[keep]])


class SilenceDetector(ShadowDetector):
    name: ClassVar[str] = "silences"
    summary: ClassVar[str] = "dark spans of the event polarity pattern (a falling run, then a rising event), any refractory period"
    options: ClassVar[tuple[Option, ...]] = (
        Option("min_gap_ms", float, -1.0, "shortest span, ms (−1: twice the refractory period, at least 0.2 ms)", minimum=-1.0),
        Option("ratio", float, 3.0, "a span must last this many times the event intervals beside it (0: off)", minimum=0.0),
    )

    def detect(self, evidence: ShadowEvidence, options: dict[str, Any]) -> ShadowMask:
        found = dark_spans(
            evidence.profile, refractory_us=evidence.refractory_us,
            min_gap_us=min_gap_us(options["min_gap_ms"], evidence.refractory_us, 2.0), ratio=options["ratio"],
        )
        return evidence.event_mask(found)


def min_gap_us(min_gap_ms: float, refractory_us: float, periods: float) -> float:
    """``min_gap_ms`` in µs, or (−1) ``periods`` refractory periods and at least 200 µs."""
    return 1000.0 * min_gap_ms if min_gap_ms >= 0 else max(periods * refractory_us, 200.0)
