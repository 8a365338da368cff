"""Coarse normals at the super pixels from their events alone (the EventPS relation, Yu et al., CVPR 2024), the
"from super pixels" source of supplement Table 1 for frame pixels with fewer than three effective
lights.

A Lambertian super pixel satisfies n·l(t) = e^Δ·n·l(t_ref) for each event pair of preprocessing
whose log irradiance rises by Δ from t_ref to t (albedo and light strength cancel), so each pair
gives n·v = 0 with v = e^Δ l(t_ref) − l(t), l the light direction times its grey intensity. The normal is the
eigenvector of Σ w v vᵀ/|v|² with the smallest eigenvalue (w the pair's confidence), flipped so
n_z ≥ 0, where the pairs span at least two directions.
"""

from __future__ import annotations

import numpy as np

from pstoolkit import LightModel
from pstoolkit.events.relation import (
    Constraints,
    accumulate,
    grey_light,
    smallest_eigenvectors,
)

MIN_PAIRS = 3


def event_normals(
    pixel: np.ndarray,
    t_ref_us: np.ndarray,
    t_us: np.ndarray,
    target: np.ndarray,
    weight: np.ndarray,
    light: LightModel,
    *,
    n_pixels: int,
) -> tuple[np.ndarray, np.ndarray]:
    """(n_pixels, 3) unit normals and (n_pixels,) bool where determined, from the event pairs
    (``pixel``, reference and event times, log change Δ ``target``, confidence ``weight``)."""
    t_now = np.asarray(t_us, dtype=np.float64)
    v = np.exp(np.asarray(target, dtype=np.float64)) * grey_light(light, np.asarray(t_ref_us, dtype=np.float64)) - grey_light(light, t_now)
    squared = np.einsum("in,in->n", v, v)
    good = (squared > 0) & (np.asarray(weight) > 0)
    constraints = Constraints(pixel=np.asarray(pixel)[good], t_us=t_now[good], v=v[:, good],
                              weight=np.asarray(weight, dtype=np.float64)[good] / squared[good])
    sums, counts = accumulate(constraints.pixel, constraints, n_pixels)
    return smallest_eigenvectors(sums, counts, MIN_PAIRS)
