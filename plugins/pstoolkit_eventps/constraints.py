"""EventPS constraints (facts §5): each pair of consecutive events of a pixel gives n·v = 0, and the
normal is the smallest eigenvector of the per-pixel sum of v vᵀ (``pstoolkit.eventnormals``).

For a Lambertian pixel the irradiance is ρ·(n·l(t)), so two consecutive events k−1, k with
polarity p_k satisfy n·l(t_k) = e^{p_k C} n·l(t_ref): albedo and light strength cancel. With the
refractory rule of ``pstoolkit.eventmodel`` the earlier level is the one at t_ref = t_{k−1} + R.
Hence v = e^{C⁺} l(t_ref) − l(t_k) for p = +1 and v = e^{C⁻} l(t_k) − l(t_ref) for p = −1, where
l(t) is the light direction times its grey intensity (the sensor's luma weights).

Each v is weighted by 1/|v|² (a unit constraint), so every pair counts once whatever the light's speed.
"""

from __future__ import annotations

import numpy as np

from psfmt import EventArray
from pstoolkit.eventmodel import consecutive_pairs, reference_time_us
from pstoolkit.eventnormals import Constraints, grey_light
from pstoolkit.lights import LightModel


def grey_lights_at(light: LightModel, *times_us: np.ndarray) -> list[np.ndarray]:
    """``grey_light`` at each array of integer µs times. When the times cover fewer distinct µs than
    there are times (one turn of a ring is 33 333 µs, and one turn of events at 256² holds ~300 000
    times) the light is evaluated once per µs of the span and looked up: the same values at a
    fraction of the cost."""
    total = sum(t.size for t in times_us)
    if total == 0:
        return [np.empty((3, 0)) for _ in times_us]
    lo = min(int(t.min()) for t in times_us if t.size)
    hi = max(int(t.max()) for t in times_us if t.size)
    if hi - lo + 1 >= total:
        return [grey_light(light, t.astype(np.float64)) for t in times_us]
    table = grey_light(light, np.arange(lo, hi + 1, dtype=np.float64))
    return [table[:, t - lo] for t in times_us]


def pair_constraints(
    events: EventArray,
    width: int,
    light: LightModel,
    *,
    contrast_pos: float,
    contrast_neg: float,
    refractory_us: float,
    min_interval_us: float,
    max_interval_us: float,
) -> tuple[Constraints, int]:
    """The constraints of every pair of consecutive same-pixel events whose interval lies in
    [min_interval_us, max_interval_us]; also returns the number of pairs before that filter. A
    long interval means the pixel sat in shadow (or was dark) in between, where the Lambertian
    relation does not hold; one shorter than the refractory period is not a sensor event pair."""
    pairs = consecutive_pairs(events, width)
    interval = pairs.t_us - pairs.t_prev_us
    keep = (interval >= min_interval_us) & (interval <= max_interval_us)
    t_now = pairs.t_us[keep]
    t_ref = reference_time_us(pairs.t_prev_us[keep], refractory_us)
    if float(refractory_us).is_integer():
        l_ref, l_now = grey_lights_at(light, t_ref.astype(np.int64), t_now)
    else:
        l_ref, l_now = grey_light(light, t_ref), grey_light(light, t_now.astype(np.float64))
    # v and −v give the same constraint, so p = −1's v is written as l_ref − e^{C⁻} l_now.
    rising = pairs.p[keep] > 0
    v = np.where(rising, np.exp(contrast_pos), 1.0) * l_ref - np.where(rising, 1.0, np.exp(contrast_neg)) * l_now
    squared = np.einsum("in,in->n", v, v)
    good = squared > 0
    return (
        Constraints(pixel=pairs.pixel[keep][good], t_us=t_now[good], v=v[:, good], weight=1.0 / squared[good]),
        len(interval),
    )
