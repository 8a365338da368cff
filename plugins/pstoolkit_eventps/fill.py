"""Normals for the event pixels whose own constraints do not determine one (``pstoolkit_eventps.eventps``):
the swing of a ring light, or the neighbours' constraints, and the confidence levels that say which.

**Swing.** Under a directional light circling the camera axis at zenith θ, a Lambertian pixel with
normal n = (sin α cos β, sin α sin β, cos α) sees n·l(φ) = cos α cos θ (1 + t cos(φ − β)) with
t = tan α · tan θ, so over one turn its log-irradiance swings by S = ln((1 + t)/(1 − t)) = 2 artanh t
whatever its albedo. Over turns it fires about one rising and one falling event per C of swing, so
N events a turn mean S ∈ [C·N/2, C·(N/2 + 1)); the estimate takes the middle, S = C·(N/2 + ½), and
tan α = tanh(S/2) / tan θ. A silent pixel never moved C from the level it started at, so S < 2C
(tan α < tanh(C) / tan θ) and its azimuth is unknown: it gets the axis itself. The irradiance rises while the light moves towards the normal's azimuth,
so the rising events sit where the light's motion across the image plane, m(t), has a positive
component along the normal's tilt: Σ p_k m(t_k) points along (cos β, sin β). The argument needs
the window to span a turn of a light that circles the axis (``LightPath.circles_axis``); it ignores
shadows, and a pixel that fires few events because it sits in a shadow most of the turn gets a tilt
that is too small.

**Neighbours.** Where the swing does not apply (a window shorter than a turn, a light that does not
circle the axis), a pixel without a fit takes the smallest eigenvector of its own and its
neighbours' constraint sums over the smallest square (radius ``NEIGHBOUR_RADII``) that holds at
least ``min_pairs`` constraints of rank 2; a pixel with none within the largest takes the axis.
"""

from __future__ import annotations

import numpy as np

from pstoolkit.events.relation import smallest_eigenvectors

FIT = 1.0
"""Confidence of a pixel whose own constraints determine its normal (rank 2, at least ``min_pairs``)."""
NEIGHBOURS = 0.5
"""Confidence of a pixel whose normal comes from its and its neighbours' constraints."""
SWING = 0.25
"""Confidence of a pixel whose normal comes from the swing of the ring light (or silence)."""
SOURCES = {"fit": FIT, "neighbours": NEIGHBOURS, "swing": SWING}
NEIGHBOUR_RADII = (1, 2, 4, 8)
"""Half-widths (event pixels) of the squares searched for neighbours' constraints, in turn."""
AXIS = np.array([0.0, 0.0, 1.0])
OUTLIER_DEG = 20.0
"""A fit farther than this from the mean of its neighbours' normals is an outlier (``isolated_outliers``):
blobs and relief at 128 px lose 0.1° and 0.5° of MAE, and 0.3° and 0.9° with background events,
where 15° costs relief 0.2° more and 10° its 90th percentile."""
OUTLIER_NEIGHBOURS = 3
"""Fewest neighbours with a fit of their own that can overrule a pixel's fit."""
HOT_RATIO = 3.0
HOT_MARGIN = 32
"""A pixel is hot when it fires more than ``HOT_RATIO`` × the median of its neighbours + ``HOT_MARGIN``
events (``hot_pixels``); the margin keeps a pixel beside silent ones from counting for a few events."""


def swing_normals(fired: np.ndarray, swing: np.ndarray, turns: float, contrast: float, tan_zenith: float) -> np.ndarray:
    """Unit normals (P, 3) from the swing argument (module docstring): ``fired`` (P,) events per pixel
    over ``turns`` turns of the light, ``swing`` (P, 2) the sum of p·m(t) over them, ``contrast``
    the (mean) threshold C and ``tan_zenith`` the tangent of the light's zenith angle."""
    log_swing = np.where(fired > 0, (fired / turns / 2.0 + 0.5) * contrast, 0.0)
    length = np.hypot(swing[:, 0], swing[:, 1])
    tilt = np.where(length > 0, np.arctan(np.tanh(log_swing / 2.0) / tan_zenith), 0.0)
    scale = np.sin(tilt) / np.where(length > 0, length, 1.0)
    return np.stack([scale * swing[:, 0], scale * swing[:, 1], np.cos(tilt)], axis=-1)


def hot_pixels(fired: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(P,) bool of the pixels that fired (``fired`` (P,) events, (H, W) = ``shape``) more than
    ``HOT_RATIO`` times the median of their eight neighbours and ``HOT_MARGIN`` more: a pixel on a
    smooth surface fires about as often as its neighbours, a hot pixel on its own (leakage, a defect).
    Only pixels above the margin are looked at, so the test costs next to nothing per window."""
    counts = fired.reshape(shape)
    hot = np.zeros(counts.size, dtype=bool)
    candidates = np.flatnonzero(counts.reshape(-1) > HOT_MARGIN)
    if candidates.size:
        padded = np.pad(counts, 1, mode="edge")
        y, x = np.divmod(candidates, shape[1])
        around = np.stack([padded[1 + y + dy, 1 + x + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx])
        hot[candidates] = counts.reshape(-1)[candidates] > HOT_RATIO * np.median(around, axis=0) + HOT_MARGIN
    return hot


def _ring_sums(image: np.ndarray) -> np.ndarray:
    """Sums of ``image`` (H, W, K) over each pixel's eight neighbours (zero beyond the border)."""
    h, w = image.shape[:2]
    padded = np.pad(image, ((1, 1), (1, 1), (0, 0)))
    total = np.zeros_like(image, dtype=np.float64)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dy or dx:
                total += padded[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w]
    return total


def _box_sums(image: np.ndarray, radius: int) -> np.ndarray:
    """Sums of ``image`` (H, W, K) over the (2r + 1)² square around each pixel, clipped at the border."""
    h, w = image.shape[:2]
    integral = np.zeros((h + 1, w + 1, image.shape[2]))
    np.cumsum(np.cumsum(image, axis=0), axis=1, out=integral[1:, 1:])
    top, bottom = np.clip(np.arange(h) - radius, 0, h), np.clip(np.arange(h) + radius + 1, 0, h)
    left, right = np.clip(np.arange(w) - radius, 0, w), np.clip(np.arange(w) + radius + 1, 0, w)
    return (
        integral[bottom][:, right] - integral[top][:, right] - integral[bottom][:, left] + integral[top][:, left]
    )


def neighbourhoods(pixels: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Flat indices (k, 9) of each of ``pixels``' (k,) 3×3 neighbourhood on a (H, W) = ``shape`` grid,
    −1 beyond the border."""
    y, x = np.divmod(np.asarray(pixels, dtype=np.int64), shape[1])
    dy, dx = np.divmod(np.arange(9), 3)
    ny, nx = y[:, None] + dy - 1, x[:, None] + dx - 1
    inside = (ny >= 0) & (ny < shape[0]) & (nx >= 0) & (nx < shape[1])
    return np.where(inside, ny * shape[1] + nx, -1)


def neighbour_mean(normal: np.ndarray, neighbourhood: np.ndarray) -> np.ndarray:
    """The normalised mean (k, 3) of the normals (``normal`` (P, 3)) of each row of ``neighbourhood``
    (k, 9) flat indices (``neighbourhoods``; −1 left out); zero where the sum is."""
    total = np.einsum("kn,knc->kc", (neighbourhood >= 0).astype(np.float64), normal[np.maximum(neighbourhood, 0)])
    length = np.sqrt(np.einsum("kc,kc->k", total, total))
    return total / np.where(length > 0, length, 1.0)[:, None]


def isolated_outliers(normal: np.ndarray, fit: np.ndarray, shape: tuple[int, int],
                      max_deg: float = OUTLIER_DEG) -> tuple[np.ndarray, np.ndarray]:
    """The normalised mean (P, 3) of the own fits among each pixel's eight neighbours (``normal``
    (P, 3) on a (H, W) = ``shape`` grid, ``fit`` (P,) bool) and the (P,) bool of the fits more than
    ``max_deg`` from it, where at least ``OUTLIER_NEIGHBOURS`` neighbours have a fit: a surface's
    normals change little from one pixel to the next, so a fit that disagrees with its neighbours'
    together comes from pairs the model does not explain (noise events, a highlight). Filled
    neighbours do not count: a silent background beside a limb would pull the limb to the axis."""
    stacked = np.concatenate([normal * fit[:, None], fit[:, None].astype(np.float64)], axis=1)
    total = _ring_sums(stacked.reshape(shape + (4,))).reshape(-1, 4)
    length = np.sqrt(np.einsum("pc,pc->p", total[:, :3], total[:, :3]))
    mean = total[:, :3] / np.where(length > 0, length, 1.0)[:, None]
    cosine = np.einsum("pc,pc->p", mean, normal)
    enough = total[:, 3] >= OUTLIER_NEIGHBOURS - 0.5
    return mean, fit & enough & (length > 0) & (cosine < np.cos(np.radians(max_deg)))


def _matrices(six: np.ndarray) -> np.ndarray:
    """(B, 3, 3) symmetric matrices from their unique entries (B, 6): xx xy xz yy yz zz."""
    rows = np.array([[0, 1, 2], [1, 3, 4], [2, 4, 5]])
    return six[:, rows]


def neighbour_normals(
    sums: np.ndarray, count: np.ndarray, need: np.ndarray, shape: tuple[int, int], min_pairs: int
) -> tuple[np.ndarray, np.ndarray]:
    """Normals (P, 3) of the pixels in ``need`` (P,) from the pooled constraint sums (``sums`` (P, 6),
    ``count`` (P,) constraints per pixel) of the smallest square around them that determines one
    (module docstring), and the (P,) bool of those found."""
    normal = np.zeros((len(need), 3))
    found = np.zeros(len(need), dtype=bool)
    image = np.concatenate([sums, count[:, None].astype(np.float64)], axis=1).reshape(shape + (7,))
    for radius in NEIGHBOUR_RADII:
        todo = np.flatnonzero(need & ~found)
        if todo.size == 0:
            break
        pooled = _box_sums(image, radius).reshape(-1, 7)[todo]
        n, ok = smallest_eigenvectors(_matrices(pooled[:, :6]), np.rint(pooled[:, 6]).astype(np.int64), min_pairs)
        normal[todo[ok]] = n[ok]
        found[todo[ok]] = True
    return normal, found
