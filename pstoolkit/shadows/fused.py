"""Cast shadows where the surface and the events agree (``fused``, the default of ``dualres``).

The surface (``geometry``) predicts every shadow at frame resolution but also shadows that a wrong
normal or a smoothed depth step invents; the events (``silences``) see every deep shadow of a super
pixel but also the dark spans of smooth shading. A frame pixel is taken to be in a cast shadow at a
time when both say so: the surface's shadow at that pixel, and a dark span (or no event at all over
the period) of the super pixel covering it. On simulated captures at the 2 ms recipe the mask of the
two together is far more precise than either alone (``benchmarks/dualres.py --ablation``). Before the
solver has a surface the detector returns no mask.

Light from the rest of the object fills the cast shadows of a concavity, and its events are not dark
there; so a shadow of the surface also counts where the events see its edges (``edge_seen``: a net fall
at its entry, a net rise at its exit), at the frame pixels the surface shadows for at most ``edge_share``
of the turn. A pixel shadowed longer keeps only what a dark span confirms: under inter-reflection the few
directly lit samples a longer mask leaves it fix its normal worse than the bounce-lit ones they replace
(``docs/dualres-tuning.md``).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any, ClassVar

import numpy as np

from pstoolkit.plugin.options import Option
from pstoolkit.shadows.base import ShadowDetector, ShadowEvidence, ShadowMask
from pstoolkit.shadows.edge_seen import seen_shadows
from pstoolkit.shadows.geometry import GEOMETRY_OPTIONS, shadow_height
from pstoolkit.shadows.intervals import RunCollector, rasterize
from pstoolkit.shadows.silences import dark_spans, min_gap_us
from pstoolkit.shadows.surface_sweep import surface_shadow_blocks


def event_darkness(evidence: ShadowEvidence, steps: int, min_gap: float) -> np.ndarray:
    """(steps, He·We) bool: event pixels inside a dark span, or without events over the period."""
    n_events = evidence.event_shape[0] * evidence.event_shape[1]
    spans = dark_spans(evidence.profile, refractory_us=evidence.refractory_us, min_gap_us=min_gap)
    dark = rasterize(spans, n_events, evidence.period_us, steps)
    silent = np.ones(n_events, dtype=bool)
    silent[evidence.profile.pixel] = False
    dark[:, silent] = True
    return dark


class FusedDetector(ShadowDetector):
    name: ClassVar[str] = "fused"
    summary: ClassVar[str] = "shadows of the estimated surface confirmed by dark spans or edges of the events"
    options: ClassVar[tuple[Option, ...]] = (
        *GEOMETRY_OPTIONS,
        Option("min_gap_ms", float, -1.0, "shortest dark span, ms (−1: one refractory period, at least 0.2 ms)", minimum=-1.0),
        Option("edge_share", float, 0.3, "a shadow whose edges the events see (more fall than rise within edge_tolerance_deg "
               "of its entry, more rise than fall of its exit) counts without a dark span at the pixels the surface "
               "shadows for at most this share of the turn (0: dark spans only)", minimum=0.0, maximum=1.0),
    )
    uses_surface: ClassVar[bool] = True

    def detect(self, evidence: ShadowEvidence, options: dict[str, Any]) -> ShadowMask:
        if evidence.normal is None:
            return evidence.no_mask()
        steps = options["time_steps"]
        pixels = np.flatnonzero(np.asarray(evidence.mask).ravel())
        # the height first: its solve is the detector's peak memory, better without the dark map beside it
        height, chosen = shadow_height(evidence, options)
        dark = event_darkness(evidence, steps, min_gap_us(options["min_gap_ms"], evidence.refractory_us, 1.0))
        covering = evidence.super_pixel[pixels]
        seen = None
        if options["edge_share"] > 0:
            seen = seen_shadows(evidence, height, steps, options["margin_px"], options["edge_tolerance_deg"])
            chosen = {**chosen, **seen.record()}
            # the frame pixels a seen shadow may confirm, and the column of ``seen.seen`` covering each
            column = np.full(evidence.event_shape[0] * evidence.event_shape[1], -1, dtype=np.int64)
            column[seen.columns] = np.arange(seen.columns.size)
            taking = np.flatnonzero((column[covering] >= 0) & (seen.pixel_share <= options["edge_share"]))
            taken = column[covering[taking]]
        runs = RunCollector(pixels.size)
        start = 0
        # a block of times at a time: no (steps, P) map of the surface's shadows is ever whole
        for block in surface_shadow_blocks(evidence, height, steps, options["margin_px"]):
            # np.take gathers a block's columns 5× faster than indexing with an index array
            confirmed = np.take(dark[start : start + len(block)], covering, axis=1)
            if seen is not None:
                confirmed[:, taking] |= np.take(seen.seen[start : start + len(block)], taken, axis=1)
            block &= confirmed
            runs.feed(block)
            start += len(block)
        return replace(evidence.frame_mask(runs.intervals(evidence.period_us, pixels)), diagnostics=chosen)
