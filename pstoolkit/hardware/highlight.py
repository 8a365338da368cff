"""A specular highlight on a chrome sphere → the direction towards its light, with sub-pixel precision.

The highlight is the connected region around the brightest point of the sphere above ``level`` of
the way from the sphere's median to that peak (``spot``). Its light direction is found on the
sphere, not in the image: the mean of the region's normals, weighted by how far each pixel rises
above the threshold and by the solid angle of normals it covers (1/(n·v): a pixel near the rim
spans more normals), is the lobe's centre, the half vector; the light is its mirror direction
(``mirror_direction``). Averaging normals rather than pixel positions keeps the lobe symmetric
where the sphere is foreshortened, so the centre is not pulled towards the rim.
"""

from __future__ import annotations

import numpy as np

from pstoolkit.hardware.sphere import SphereView, reflect, unit_rows

MIN_COSINE = 0.05
"""n·v below this counts as this in the solid-angle weight (the rim, where it diverges)."""


def spot(image: np.ndarray, inside: np.ndarray, level: float) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Rows, columns and weights (N,) of the highlight in ``image`` (H, W) among the pixels where
    ``inside`` (H, W) is True; weights are the rise above the threshold. None when the sphere is
    blank there."""
    from scipy import ndimage  # deferred: scipy loads only for calibration

    values = np.where(inside, image, -np.inf)
    flat = int(np.argmax(values))
    peak = float(values.flat[flat])
    background = float(np.median(image[inside]))
    if not np.isfinite(peak) or peak <= background:
        return None
    threshold = background + level * (peak - background)
    labels, _ = ndimage.label(values > threshold, structure=np.ones((3, 3)))
    rows, cols = np.nonzero(labels == labels.flat[flat])
    return rows, cols, image[rows, cols] - threshold


def mirror_direction(u: np.ndarray, v: np.ndarray, weights: np.ndarray, sphere: SphereView) -> np.ndarray:
    """Unit direction (3,) towards the light whose highlight covers frame pixels (u, v) (N,) with
    ``weights`` (N,): the weighted mean normal and view direction, mirrored."""
    n, view, _ = sphere.normals(u, v)
    w = np.asarray(weights, dtype=np.float64) / np.maximum(np.sum(n * view, axis=-1), MIN_COSINE)
    mean_n = unit_rows((w[:, None] * n).sum(axis=0))
    mean_v = unit_rows((w[:, None] * view).sum(axis=0))
    return unit_rows(reflect(mean_n, mean_v))


def disc(shape: tuple[int, int], sphere: SphereView, margin_px: float = 1.0) -> np.ndarray:
    """(H, W) bool: the pixels whose centres lie inside the sphere's outline, ``margin_px`` in."""
    c = sphere.circle
    v, u = np.mgrid[0 : shape[0], 0 : shape[1]]
    return (u - c.cx) ** 2 + (v - c.cy) ** 2 < max(c.r - margin_px, 1.0) ** 2


def highlight_direction(image: np.ndarray, sphere: SphereView, level: float, inside: np.ndarray | None = None) -> np.ndarray | None:
    """The light direction (3,) of the highlight in a grey frame (H, W), or None without one."""
    inside = disc(image.shape, sphere) if inside is None else inside
    found = spot(np.asarray(image, dtype=np.float64), inside, level)
    if found is None:
        return None
    rows, cols, weights = found
    return mirror_direction(cols.astype(np.float64), rows.astype(np.float64), weights, sphere)
