"""Accuracy of normal maps: per-pixel angular error and the summary statistics papers report.

MAE is the mean of the per-pixel angles (DiLiGenT's definition), not the arccos of the mean cosine.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from pstoolkit.errors import UserError

THRESHOLDS_DEG = (10, 20, 30)


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


def error_stats(errors: np.ndarray) -> dict[str, Any]:
    """Summary of angular errors in degrees (NaN entries, i.e. pixels outside the mask, are skipped):
    ``mae_deg``, ``median_deg``, ``below_10``/``below_20``/``below_30`` (shares 0..1 of pixels with an
    error under that many degrees) and ``n_pixels``."""
    values = np.asarray(errors, dtype=np.float64).ravel()
    values = values[~np.isnan(values)]
    if values.size == 0:
        raise UserError("no pixels to evaluate: the mask is empty")
    stats: dict[str, Any] = {"mae_deg": float(values.mean()), "median_deg": float(np.median(values))}
    for threshold in THRESHOLDS_DEG:
        stats[f"below_{threshold}"] = float(np.count_nonzero(values < threshold) / values.size)
    stats["n_pixels"] = int(values.size)
    return stats
