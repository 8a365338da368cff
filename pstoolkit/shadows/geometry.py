"""Cast shadows of the estimated surface (``geometry``): the solver's current normals integrated into
a height map (``pstoolkit.surface``), then marched towards the light on a time grid with the
simulator's shadow sweep (``pstoolkit.optics.shadow_sweep.shadow_margin``), at frame resolution.

Cast shadows are a function of the shape and the light alone, so a good normal map predicts them
exactly and at the frame pixels' own resolution; what it cannot see are depth steps at occluding
contours (normals only give slopes), which the integration spreads over a few pixels, so a shadow a
step casts comes out too short; and a relief whose normals are flattened (inter-reflection in a
concavity) casts all its shadows too short, so the height is marched at the scale whose shadow edges
the events confirm (``pstoolkit.shadows.height_scale``, option ``height_scale``). ``fused`` checks the
prediction against the events.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any, ClassVar

import numpy as np

from pstoolkit.plugin.options import Option
from pstoolkit.shadows.base import ShadowDetector, ShadowEvidence, ShadowMask
from pstoolkit.shadows.device_tracking import run_collector
from pstoolkit.shadows.height_scale import calibrate
from pstoolkit.shadows.surface_sweep import surface_height, surface_shadow_blocks

GEOMETRY_OPTIONS: tuple[Option, ...] = (
    Option("time_steps", int, 720, "light directions per period the shadows are marched towards", minimum=8, maximum=100000),
    Option("margin_px", float, 0.225, "an occluder must rise this many pixels above a ray to shadow it", minimum=-10.0, maximum=10.0),
    Option("height_scale", float, 0.0, "factor on the integrated height before the sweep; 0 = the scale whose shadow "
           "edges the events' onsets confirm best (pstoolkit.shadows.height_scale)", minimum=0.0, maximum=10.0),
    Option("edge_tolerance_deg", float, 10.0, "how far (degrees of the turn) the events that confirm a predicted shadow "
           "edge may lie from it (height_scale 0; fused's edge_share)", minimum=0.1, maximum=90.0),
)


def shadow_height(evidence: ShadowEvidence, options: dict[str, Any]) -> tuple[np.ndarray, dict[str, Any]]:
    """(H, W) float32 height map (pixels) the detectors march — ``surface_height`` times ``height_scale``,
    calibrated against the events' onsets when that is 0 (``height_scale.calibrate``) — and the
    diagnostics of the choice. Once per surface and options (``ShadowEvidence.of_surface``): the map is
    read-only."""
    key = ("shadow_height", *(options[name] for name in ("height_scale", "margin_px", "edge_tolerance_deg")))
    height, record = evidence.of_surface(key, lambda: _shadow_height(evidence, options))
    return height, dict(record)


def _shadow_height(evidence: ShadowEvidence, options: dict[str, Any]) -> tuple[np.ndarray, dict[str, Any]]:
    height = _read_only(surface_height(evidence))
    if options["height_scale"] > 0:
        return _read_only(height * np.float32(options["height_scale"])), {"height_scale": options["height_scale"]}
    chosen = calibrate(evidence, height, margin_px=options["margin_px"], tolerance_deg=options["edge_tolerance_deg"])
    return _read_only(height * np.float32(chosen.scale)), chosen.record()


def _read_only(array: np.ndarray) -> np.ndarray:
    array.flags.writeable = False
    return array


class GeometryDetector(ShadowDetector):
    name: ClassVar[str] = "geometry"
    summary: ClassVar[str] = "cast shadows ray-marched on the height map integrated from the solver's normals"
    options: ClassVar[tuple[Option, ...]] = GEOMETRY_OPTIONS
    uses_surface: ClassVar[bool] = True

    def detect(self, evidence: ShadowEvidence, options: dict[str, Any]) -> ShadowMask:
        if evidence.normal is None:
            return evidence.no_mask()
        pixels = np.flatnonzero(np.asarray(evidence.mask).ravel())
        runs = run_collector(pixels.size, evidence.device)
        height, chosen = shadow_height(evidence, options)
        for block in surface_shadow_blocks(evidence, height, options["time_steps"], options["margin_px"]):
            runs.feed(block)
        return replace(evidence.frame_mask(runs.intervals(evidence.period_us, pixels)), diagnostics=chosen)
