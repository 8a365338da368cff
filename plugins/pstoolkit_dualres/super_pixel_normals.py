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
    """Unit normals of the super pixels from their event pairs (see the module docstring).

    Parameters
    ----------
    pixel
        (K,) flat event pixel of each pair.
    t_ref_us, t_us
        (K,) reference and event times of each pair, µs on the light's clock.
    target
        (K,) log change Δ from ``t_ref_us`` to ``t_us``.
    weight
        (K,) confidence w of each pair (≤ 0: ignored).
    light
        The directional light model.
    n_pixels
        Number of super pixels (event pixels).

    Returns
    -------
    normal : numpy.ndarray
        (n_pixels, 3) unit normals with n_z ≥ 0; zero where not determined.
    determined : numpy.ndarray
        (n_pixels,) bool: at least ``MIN_PAIRS`` pairs spanning at least two directions.
    """
    t_now = np.asarray(t_us, dtype=np.float64)
    v = np.exp(np.asarray(target, dtype=np.float64)) * grey_light(light, np.asarray(t_ref_us, dtype=np.float64)) - grey_light(light, t_now)
    squared = np.einsum("in,in->n", v, v)
    good = (squared > 0) & (np.asarray(weight) > 0)
    constraints = Constraints(pixel=np.asarray(pixel)[good], t_us=t_now[good], v=v[:, good],
                              weight=np.asarray(weight, dtype=np.float64)[good] / squared[good])
    sums, counts = accumulate(constraints.pixel, constraints, n_pixels)
    return smallest_eigenvectors(sums, counts, MIN_PAIRS)
