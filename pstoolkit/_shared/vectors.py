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
