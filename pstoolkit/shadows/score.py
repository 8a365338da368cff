"""Shadow masks against the truth of a simulated capture: the cast shadows its ground-truth depth
casts (the simulator's own sweep), and precision and recall per pixel-time.

    truth = true_shadows(capture.ground_truth.depth, capture.ground_truth.mask, light, t0_us, period_us)
    precision, recall = score(mask, truth, capture.ground_truth.mask)
"""

from __future__ import annotations

import numpy as np

from pstoolkit.optics.lights import LightModel
from pstoolkit.shadows.base import ShadowMask
from pstoolkit.shadows.intervals import grid_times, intervals_from_grid

SCORE_STEPS = 1440


def true_shadows(depth: np.ndarray, mask: np.ndarray, light: LightModel, t0_us: float, period_us: float,
                 steps: int = SCORE_STEPS) -> ShadowMask:
    """The cast shadows (V < ½ in the simulator's soft-edged visibility) of a height map under a light,
    as a frame-resolution mask.

    Parameters
    ----------
    depth
        (H, W) height map, towards the camera, in pixels.
    mask
        (H, W) bool, the object's pixels; only they occlude.
    light
        The directional light model.
    t0_us, period_us
        Start of the period and its length, µs.
    steps
        Light directions per period, at the bin centres of ``grid_times``.

    Returns
    -------
    ShadowMask
        The shadow intervals of every frame pixel, per period from ``t0_us``.
    """
    from pstoolkit.optics.shadow_sweep import cast_shadow_mask  # deferred: compiled with numba

    mask = np.asarray(mask, dtype=bool)
    directions = light.evaluate(t0_us + grid_times(period_us, steps))[0]
    inside = mask.ravel()
    shadowed = cast_shadow_mask(np.asarray(depth, dtype=np.float32), mask, directions).reshape(steps, -1)[:, inside]
    found = intervals_from_grid(shadowed, period_us, np.flatnonzero(inside))
    return ShadowMask.from_intervals(found, np.arange(mask.size), t0_us, period_us)


def score(mask: ShadowMask, truth: ShadowMask, region: np.ndarray, steps: int = SCORE_STEPS) -> tuple[float, float]:
    """(precision, recall) of ``mask`` against ``truth`` over the frame pixels of ``region`` (H, W)
    and ``steps`` times per period: the share of pixel-times the mask calls shadowed that are, and
    the share of shadowed pixel-times it calls so (1.0 where there is nothing to find or call)."""
    pixels = np.flatnonzero(np.asarray(region, dtype=bool).ravel())
    times = truth.t0_us + grid_times(truth.period_us, steps)
    p = np.tile(pixels, steps)
    t = np.repeat(times, pixels.size)
    said, true = mask.contains(p, t), truth.contains(p, t)
    hits = float(np.sum(said & true))
    return (hits / said.sum() if said.any() else 1.0), (hits / true.sum() if true.any() else 1.0)


