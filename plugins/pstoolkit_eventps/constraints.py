"""EventPS constraints (facts §5): each pair of consecutive events of a pixel gives n·v = 0, and the
normal is the smallest eigenvector of the per-pixel sum of v vᵀ.

For a Lambertian pixel the irradiance is ρ·(n·l(t)), so two consecutive events k−1, k with
polarity p_k satisfy n·l(t_k) = e^{p_k C} n·l(t_ref): albedo and light strength cancel. With the
refractory rule of ``pstoolkit.eventmodel`` the earlier level is the one at t_ref = t_{k−1} + R.
Hence v = e^{C⁺} l(t_ref) − l(t_k) for p = +1 and v = e^{C⁻} l(t_k) − l(t_ref) for p = −1, where
l(t) is the light direction times its grey intensity (the sensor's luma weights).

Each v is weighted by 1/|v|² (a unit constraint), so every pair counts once whatever the light's speed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from psfmt import EventArray
from pstoolkit.eventmodel import GREY_WEIGHTS, consecutive_pairs, reference_time_us
from pstoolkit.lights import LightModel

# The upper triangle of a symmetric 3×3 matrix, in the order the sums are accumulated.
_ROWS = np.array([0, 0, 0, 1, 1, 2])
_COLS = np.array([0, 1, 2, 1, 2, 2])
# A pixel's constraints determine n when the middle eigenvalue of Σ v vᵀ exceeds this share of the
# largest (rank ≥ 2): below it the pairs' v are nearly parallel and n may turn freely about them.
MIN_RANK_RATIO = 1e-3


@dataclass
class Constraints:
    """Constraint vectors ``v`` (3, N), component-major so each component is contiguous, their
    weights 1/|v|² (N,), the flat event pixel (y·width + x) and the later event's time ``t_us`` of
    the pair each came from; pixels grouped, times increasing within one."""

    pixel: np.ndarray
    t_us: np.ndarray
    v: np.ndarray
    weight: np.ndarray


def grey_light(light: LightModel, t_us: np.ndarray) -> np.ndarray:
    """l(t) = direction × luma of the RGB intensity, (3, N) component-major."""
    direction, intensity = light.evaluate(t_us)
    return (direction * (intensity @ np.asarray(GREY_WEIGHTS))[:, None]).T


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


def accumulate(bins: np.ndarray, constraints: Constraints, n_bins: int) -> tuple[np.ndarray, np.ndarray]:
    """Σ w v vᵀ per bin as (n_bins, 3, 3) and the number of constraints per bin; six bincounts over
    the unique entries of the symmetric matrix."""
    v, w = constraints.v, constraints.weight
    sums = np.empty((n_bins, 3, 3))
    for r, c in zip(_ROWS, _COLS):
        sums[:, r, c] = np.bincount(bins, weights=v[r] * v[c] * w, minlength=n_bins)
        sums[:, c, r] = sums[:, r, c]
    return sums, np.bincount(bins, minlength=n_bins)


def symmetric_eigen(sums: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues (B, 3) in ascending order and the unit eigenvector of the smallest (B, 3) of
    symmetric 3×3 matrices, in closed form (Smith 1961): the trigonometric solution of the
    characteristic cubic, then the eigenvector as the longest cross product of two rows of
    A − λ_min·I. Written on the six unique entries as flat arrays, it is several times faster than
    batched LAPACK ``eigh`` on many tiny matrices, and as accurate when the smallest eigenvalue is
    separated from the middle one (which the rank test of ``smallest_eigenvectors`` requires)."""
    a, b, c = sums[:, 0, 0], sums[:, 0, 1], sums[:, 0, 2]
    d, e, f = sums[:, 1, 1], sums[:, 1, 2], sums[:, 2, 2]
    q = (a + d + f) / 3.0
    a0, d0, f0 = a - q, d - q, f - q
    p = np.sqrt((a0 * a0 + d0 * d0 + f0 * f0 + 2.0 * (b * b + c * c + e * e)) / 6.0)
    det = a0 * (d0 * f0 - e * e) - b * (b * f0 - e * c) + c * (b * e - d0 * c)
    cube = np.where(p > 0, p, 1.0) ** 3
    phi = np.arccos(np.clip(det / (2.0 * cube), -1.0, 1.0)) / 3.0
    largest = q + 2.0 * p * np.cos(phi)
    smallest = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    values = np.stack([smallest, 3.0 * q - largest - smallest, largest], axis=1)
    a1, d1, f1 = a - smallest, d - smallest, f - smallest
    # rows of A − λI: (a1, b, c), (b, d1, e), (c, e, f1); their three pairwise cross products
    crosses = np.stack(
        [
            np.stack([b * e - c * d1, c * b - a1 * e, a1 * d1 - b * b]),
            np.stack([b * f1 - c * e, c * c - a1 * f1, a1 * e - b * c]),
            np.stack([d1 * f1 - e * e, e * c - b * f1, b * e - d1 * c]),
        ]
    )  # (3 pairs, 3 components, B)
    lengths = np.sqrt(np.einsum("pkb,pkb->pb", crosses, crosses))
    best = np.argmax(lengths, axis=0)
    columns = np.arange(len(sums))
    vector = crosses[best, :, columns]
    norm = lengths[best, columns]
    vector /= np.where(norm > 0, norm, 1.0)[:, None]
    return values, vector


def smallest_eigenvectors(sums: np.ndarray, counts: np.ndarray, min_pairs: int) -> tuple[np.ndarray, np.ndarray]:
    """Per bin, the unit eigenvector of the smallest eigenvalue, flipped to n_z ≥ 0, for bins with at
    least ``min_pairs`` constraints of rank ≥ 2; zero elsewhere. Returns normals (B, 3) and the
    (B,) bool of determined bins."""
    normal = np.zeros((len(counts), 3))
    candidate = np.flatnonzero(counts >= max(min_pairs, 2))
    values, vectors = symmetric_eigen(sums[candidate])
    determined = values[:, 1] > MIN_RANK_RATIO * values[:, 2]
    n = vectors[determined]
    n *= np.where(n[:, 2] < 0, -1.0, 1.0)[:, None]
    ok = np.zeros(len(counts), dtype=bool)
    ok[candidate[determined]] = True
    normal[ok] = n
    return normal, ok
