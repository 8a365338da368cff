"""Cast shadows of the estimated surface (``geometry``): the solver's current normals integrated into
a height map (``pstoolkit.surface``), then marched towards the light on a time grid with the
simulator's shadow sweep (``pstoolkit.optics.shadow_sweep.shadow_margin``), at frame resolution.

Cast shadows are a function of the shape and the light alone, so a good normal map predicts them
exactly and at the frame pixels' own resolution; what it cannot see are depth steps at occluding
contours (normals only give slopes), which the integration spreads over a few pixels, so a shadow a
step casts comes out too short. ``fused`` checks the prediction against the events.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any, ClassVar

import numpy as np

from pstoolkit.plugin.options import Option
from pstoolkit.shadows.base import ShadowDetector, ShadowEvidence, ShadowMask
from pstoolkit.shadows.intervals import RunCollector, grid_times

# Light directions swept at once: bounds the (chunk, H, W) float32 margins held in memory.
SWEEP_CHUNK = 32
GEOMETRY_OPTIONS: tuple[Option, ...] = (
    Option("time_steps", int, 720, "light directions per period the shadows are marched towards", minimum=8, maximum=100000),
    Option("margin_px", float, 0.225, "an occluder must rise this many pixels above a ray to shadow it", minimum=-10.0, maximum=10.0),
)


def surface_height(evidence: ShadowEvidence) -> np.ndarray:
    """(H, W) float32 height map (pixels) of the surface ``evidence.normal`` (not None), integrated
    over ``evidence.mask`` (``pstoolkit.surface.integrate_normals``)."""
    from pstoolkit.surface import integrate_normals

    mask = np.asarray(evidence.mask, dtype=bool)
    return integrate_normals(np.asarray(evidence.normal, dtype=np.float64), mask).astype(np.float32)


def surface_shadow_blocks(evidence: ShadowEvidence, height: np.ndarray, time_steps: int, margin_px: float) -> Iterator[np.ndarray]:
    """Cast shadows of the surface of ``height`` (``surface_height``) at the bin centres of
    ``intervals.grid_times`` from ``evidence.t0_us``, as blocks of up to SWEEP_CHUNK times in order:
    (n, P) bool each, P the masked frame pixels in flat order. A block is a view of a buffer the
    next one overwrites: use it (or copy it) before asking for the next. The whole (time_steps, P)
    map never exists (0.75 GB at 1024² pixels and 720 steps)."""
    # deferred: the sweep is compiled with numba, which `pstoolkit plugins` need not load
    from pstoolkit.optics.shadow_sweep import ShadowCaster

    mask = np.asarray(evidence.mask, dtype=bool)
    directions = evidence.light.evaluate(evidence.t0_us + grid_times(evidence.period_us, time_steps))[0]
    inside = np.flatnonzero(mask.ravel())
    # one caster (the height map in its four sweep orientations) and one set of buffers for all blocks
    caster = ShadowCaster(height, mask)
    margin = np.empty((min(SWEEP_CHUNK, time_steps), *mask.shape), dtype=np.float32)
    above = np.empty((len(margin), mask.size), dtype=bool)
    out = np.empty((len(margin), inside.size), dtype=bool)
    for start in range(0, time_steps, SWEEP_CHUNK):
        block = directions[start : start + SWEEP_CHUNK]
        n = len(block)
        caster.margins(block, margin[:n])
        # compared first, then the object's columns taken: a byte per cell moves instead of four, and
        # np.take by index is several times faster than a boolean mask or np.compress along axis 1
        np.greater(margin[:n].reshape(n, -1), margin_px, out=above[:n])
        np.take(above[:n], inside, axis=1, out=out[:n])
        yield out[:n]


class GeometryDetector(ShadowDetector):
    name: ClassVar[str] = "geometry"
    summary: ClassVar[str] = "cast shadows ray-marched on the height map integrated from the solver's normals"
    options: ClassVar[tuple[Option, ...]] = GEOMETRY_OPTIONS
    uses_surface: ClassVar[bool] = True

    def detect(self, evidence: ShadowEvidence, options: dict[str, Any]) -> ShadowMask:
        if evidence.normal is None:
            return evidence.no_mask()
        pixels = np.flatnonzero(np.asarray(evidence.mask).ravel())
        runs = RunCollector(pixels.size)
        for block in surface_shadow_blocks(evidence, surface_height(evidence), options["time_steps"], options["margin_px"]):
            runs.feed(block)
        return evidence.frame_mask(runs.intervals(evidence.period_us, pixels))
