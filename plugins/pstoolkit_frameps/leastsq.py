"""Batched weighted least squares of Lambertian shading, b = ρ·n, over all pixels at once."""

from __future__ import annotations

import numpy as np

MIN_OBSERVATIONS = 3
# A pixel whose normal matrix has a smallest/largest eigenvalue ratio below this is left out: its
# lights (after robust selection) are nearly coplanar and b is not determined.
MIN_EIGEN_RATIO = 1e-6


def robust_weights(
    grey: np.ndarray, saturated: np.ndarray, dark_fraction: float
) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel, keep observations that are neither saturated nor among the darkest
    ``dark_fraction`` of the K frames (attached and cast shadows). ``grey`` and ``saturated`` are
    (K, P). A pixel left with fewer than three observations keeps them all. Returns the (K, P) bool
    weights and the (P,) bool of pixels that fell back."""
    k = grey.shape[0]
    drop = int(np.floor(dark_fraction * k))
    rank = np.empty_like(grey, dtype=np.int32)
    np.put_along_axis(rank, np.argsort(grey, axis=0, kind="stable"), np.arange(k, dtype=np.int32)[:, None], axis=0)
    keep = (rank >= drop) & ~saturated
    fallback = keep.sum(axis=0) < MIN_OBSERVATIONS
    keep[:, fallback] = True
    return keep, fallback


def solve_shading(grey: np.ndarray, lights: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Minimise Σ_k w_kp (g_kp − L_k·b_p)² for every pixel p: ``grey`` (K, P), ``lights`` (K, 3),
    ``weights`` (K, P) bool. Returns b (P, 3) float64 (zero where undetermined) and the (P,) bool
    of pixels with ≥ 3 observations and well-conditioned normal equations."""
    w = weights.astype(np.float64)
    outer = (lights[:, :, None] * lights[:, None, :]).reshape(-1, 9)
    normal_matrix = (w.T @ outer).reshape(-1, 3, 3)
    rhs = (w * grey).T @ lights
    eigen = np.linalg.eigvalsh(normal_matrix)
    ok = (weights.sum(axis=0) >= MIN_OBSERVATIONS) & (eigen[:, 0] > MIN_EIGEN_RATIO * np.maximum(eigen[:, 2], 1e-300))
    b = np.zeros((grey.shape[1], 3))
    b[ok] = np.linalg.solve(normal_matrix[ok], rhs[ok][..., None])[..., 0]
    return b, ok
