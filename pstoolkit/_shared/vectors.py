"""Vector helpers the numpy code of every subpackage shares."""

from __future__ import annotations

import numpy as np


def unit(vectors: np.ndarray) -> np.ndarray:
    """``vectors`` (..., 3) scaled to unit length along the last axis, in their own floating dtype
    (float64 for integers); a zero vector stays zero (a normal map's background, a light that is off)."""
    vectors = np.asarray(vectors)
    if not np.issubdtype(vectors.dtype, np.floating):
        vectors = vectors.astype(np.float64)
    norm = np.linalg.norm(vectors, axis=-1, keepdims=True)
    return np.divide(vectors, norm, out=np.zeros_like(vectors), where=norm > 0)


MIN_NORMAL_LENGTH = 1e-6
"""Shortest vector a normal map holds as a normal: solvers write unit normals and exact zeros where
they solved nothing, so anything shorter (``[0, 0, 1e-30]`` in a crafted map) has no direction to trust."""


def solved_pixels(normal: np.ndarray) -> np.ndarray:
    """(...) bool of a normal map (..., 3): the pixels that hold a normal — finite and longer than
    ``MIN_NORMAL_LENGTH``. The one rule for "solved pixel" of the scores, the integrators, the
    viewer and the report."""
    length = np.linalg.norm(np.asarray(normal, dtype=np.float64), axis=-1)
    return np.isfinite(length) & (length > MIN_NORMAL_LENGTH)
