"""The EventPS relation (Yu et al., CVPR 2024, §3), shared by the ``eventps`` solver and ``dualres``'s normals at
the super pixels: pairs of events of a Lambertian pixel give constraints n·v = 0 (albedo and light
strength cancel), and the normal is the eigenvector of the smallest eigenvalue of the per-pixel
Σ w v vᵀ, in closed form for many 3×3 matrices at once.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pstoolkit.optics.grey import GREY_WEIGHTS
from pstoolkit.optics.lights import LightModel

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


def constraint_vectors(
    reference: np.ndarray, later: np.ndarray, crossed: np.ndarray, contrast_pos: np.ndarray, contrast_neg: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Unit constraint vectors v/|v| (m, 3) of relations (``pair_events``): the log level rose by
    Δ = n⁺·C⁺ − n⁻·C⁻ from the reference to the later event, so a Lambertian normal satisfies
    n·(e^{Δ/2} l_ref − e^{−Δ/2} l_now) = 0 (the symmetric split keeps both terms of order one).
    ``contrast_pos``/``contrast_neg`` are scalars or one per relation. Returns the vectors (zero where
    v = 0) and the (m,) bool of the others."""
    delta = crossed[:, 0] * contrast_pos - crossed[:, 1] * contrast_neg
    half = np.exp(0.5 * np.asarray(delta, dtype=np.float64))[:, None]
    v = half * reference - later / half
    length = np.sqrt(np.einsum("mc,mc->m", v, v))
    keep = length > 0
    return v / np.where(keep, length, 1.0)[:, None], keep
