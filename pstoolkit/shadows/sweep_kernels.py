"""Compiled kernels of the surface's shadow sweep (``surface_sweep``) and of the edges tracked on it
(``edge_tracking.EdgeTracker``), each reading a block of times row by row, rows in parallel.

- ``shadowed_columns``: the masked pixels' shadows from the sweep's margins. numpy compared the whole
  frame and then gathered the masked columns with ``np.take``, a byte at a time.
- ``reached``: whether each super pixel's shadowed share of its frame pixels reaches the edge
  threshold. numpy gathered the block's columns into super-pixel order and summed them with
  ``np.add.reduceat``: half of the height calibration's time, which sweeps 13 scales a detection.
"""

from __future__ import annotations

import numba
import numpy as np
from numba import prange


@numba.njit(cache=True, parallel=True, nogil=True)
def shadowed_columns(margin: np.ndarray, margin_px: float, inside: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover - compiled
    """``out[k, c]``: whether ``margin[k, inside[c]]`` exceeds ``margin_px``; ``margin`` (n, H·W)
    float32, ``inside`` (P,) increasing flat indices, ``out`` (n, P) bool."""
    threshold = np.float32(margin_px)
    for k in prange(out.shape[0]):
        for c in range(inside.size):
            out[k, c] = margin[k, inside[c]] > threshold


@numba.njit(cache=True, parallel=True, nogil=True)
def reached(block: np.ndarray, group: np.ndarray, needed: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover - compiled
    """``out[k, g]``: whether at least ``needed[g]`` of the columns c of ``block`` (n, P) uint8 (0 or 1)
    with ``group[c] == g`` hold 1 in row k; ``out`` (n, G) bool."""
    for k in prange(block.shape[0]):
        counts = np.zeros(needed.size, dtype=np.int32)
        for c in range(block.shape[1]):
            counts[group[c]] += block[k, c]
        for g in range(needed.size):
            out[k, g] = counts[g] >= needed[g]
