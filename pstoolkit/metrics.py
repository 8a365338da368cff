"""Accuracy of normal maps: per-pixel angular error and the summary statistics papers report.

MAE is the mean of the per-pixel angles (DiLiGenT's definition), not the arccos of the mean cosine.
A pixel a solver leaves unsolved (a zero normal) counts as 90° in the MAE, the median and the shares
under 11.25°, 22.5° and 30° (the thresholds normal-estimation papers quote); the coverage (share of
pixels solved) and the MAE over the solved pixels say how much of the error that is.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from pstoolkit.errors import UserError

THRESHOLDS_DEG = (11.25, 22.5, 30.0)
SHARE_KEYS = tuple(f"below_{threshold:g}".replace(".", "_") for threshold in THRESHOLDS_DEG)
"""The statistics' names of the shares under each threshold: below_11_25, below_22_5, below_30."""


def _unit(normal: np.ndarray) -> np.ndarray:
    norm = np.linalg.norm(normal, axis=-1, keepdims=True)
    return np.divide(normal, norm, out=np.zeros_like(normal), where=norm > 0)


def angular_error_deg(normal: np.ndarray, normal_gt: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Angle in degrees between two normal maps (..., 3), per pixel: an error map of shape (...) with
    NaN outside ``mask`` (all pixels when None). Both maps are normalised first; a zero normal counts
    as 90° off."""
    a = np.asarray(normal, dtype=np.float64)
    b = np.asarray(normal_gt, dtype=np.float64)
    if a.shape != b.shape or a.shape[-1:] != (3,):
        raise UserError(f"normal maps of shape {a.shape} and {b.shape} cannot be compared (expected equal (..., 3))")
    cosine = np.clip(np.sum(_unit(a) * _unit(b), axis=-1), -1.0, 1.0)
    errors = np.degrees(np.arccos(cosine))
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != errors.shape:
            raise UserError(f"mask of shape {mask.shape} does not fit normal maps of shape {a.shape}")
        errors[~mask] = np.nan
    return errors


def error_stats(errors: np.ndarray, solved: np.ndarray | None = None) -> dict[str, Any]:
    """Summary of angular errors in degrees over the pixels that are not NaN (NaN: outside the mask):
    ``mae_deg``, ``median_deg``, the shares (0..1) of pixels with an error under each of
    ``THRESHOLDS_DEG`` (``SHARE_KEYS``), ``n_pixels``, ``coverage`` (share of them in ``solved``, a
    bool map of the shape of ``errors``; all when None) and ``mae_solved_deg`` (MAE over those; None
    when there are none)."""
    values = np.asarray(errors, dtype=np.float64).ravel()
    inside = ~np.isnan(values)
    if not inside.any():
        raise UserError("no pixels to evaluate: the mask is empty")
    done = np.ones(values.size, dtype=bool) if solved is None else np.asarray(solved, dtype=bool).ravel()
    if done.size != values.size:
        raise UserError(f"solved map of {done.size} pixels does not fit an error map of {values.size}")
    values, done = values[inside], done[inside]
    stats: dict[str, Any] = {"mae_deg": float(values.mean()), "median_deg": float(np.median(values))}
    for threshold, key in zip(THRESHOLDS_DEG, SHARE_KEYS):
        stats[key] = float(np.count_nonzero(values < threshold) / values.size)
    stats["n_pixels"] = int(values.size)
    stats["coverage"] = float(np.count_nonzero(done) / values.size)
    stats["mae_solved_deg"] = float(values[done].mean()) if done.any() else None
    return stats
