"""Event→frame calibration from an LED-array target seen by both cameras (DualResPS supplement §3).

The LEDs are bright blobs in a frame and dense clusters in an accumulation of the events. Their
centres are matched without knowing which LED is which: every pair of small triangles (a blob and
two of its nearest neighbours) in the two images proposes an affine map; the map that brings the
most event blobs onto frame blobs wins, ties going to the one closest to the prior (the two cameras
share the field of view, so maps rotated by more than about 30° or scaled by more than 50 % from
the prior are not considered: a symmetric LED grid would otherwise match itself turned by 90°),
and a least-squares fit on its inliers refines it. Manual
correspondences are the fallback when detection is unreliable.

    fit = calibrate_target(capture)             # AffineFit: affine (2, 3), rms_px, max_px, pairs
    store_affine("target.h5", fit.affine)      # atomically, in the capture's calibration
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from itertools import combinations
from pathlib import Path

import numpy as np
from scipy import ndimage

import psfmt
from pstoolkit.errors import UserError
from pstoolkit.grid import default_affine

NEIGHBOURS = 4
MAX_DEPARTURE = 0.5
_HYPOTHESIS_BLOCK = 2048


@dataclass
class AffineFit:
    """An event→frame affine (2, 3) and how well it maps the matched LED centres: ``rms_px`` and
    ``max_px`` in frame pixels over the ``pairs`` matched centres (event (N, 2), frame (N, 2), as
    (u, v)); ``frame_blobs``/``event_blobs`` count what was detected."""

    affine: np.ndarray
    event_points: np.ndarray
    frame_points: np.ndarray
    rms_px: float
    max_px: float
    frame_blobs: int = 0
    event_blobs: int = 0

    @property
    def pairs(self) -> int:
        return len(self.event_points)


def apply_affine(affine: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Map (N, 2) points (u, v) through a (2, 3) affine."""
    return points @ affine[:, :2].T + affine[:, 2]


def fit_affine(event_points: np.ndarray, frame_points: np.ndarray) -> AffineFit:
    """Least-squares affine from corresponding centres; UserError for fewer than 3 pairs or pairs
    on one line."""
    e = np.asarray(event_points, dtype=np.float64).reshape(-1, 2)
    f = np.asarray(frame_points, dtype=np.float64).reshape(-1, 2)
    if len(e) != len(f):
        raise UserError(f"calibration: {len(e)} event points but {len(f)} frame points")
    if len(e) < 3:
        raise UserError(f"calibration: an affine needs at least 3 point pairs, got {len(e)}")
    spread = np.linalg.svd(e - e.mean(axis=0), compute_uv=False)
    if spread[1] <= 1e-9 * max(1.0, spread[0]):
        raise UserError("calibration: the event points lie on one line, so the affine is undetermined")
    design = np.hstack([e, np.ones((len(e), 1))])
    solution, *_ = np.linalg.lstsq(design, f, rcond=None)
    affine = solution.T
    residual = np.linalg.norm(apply_affine(affine, e) - f, axis=1)
    return AffineFit(affine, e, f, float(np.sqrt(np.mean(residual**2))), float(residual.max()))


def _gaussian_peaks(weights: np.ndarray, peaks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel peaks from the three-point Gaussian fit (a parabola through the logarithms of the
    peak pixel and its neighbours, exact for a sampled Gaussian) along each axis; ``ok`` is False
    where a peak is flat (saturated) or touches the border, so the fit does not apply."""
    h, w = weights.shape
    r, c = peaks[:, 0], peaks[:, 1]
    inside = (r > 0) & (r < h - 1) & (c > 0) & (c < w - 1)
    r, c = np.clip(r, 1, h - 2), np.clip(c, 1, w - 2)
    out = np.empty((len(peaks), 2))
    ok = inside.copy()
    with np.errstate(divide="ignore", invalid="ignore"):
        for axis, (dr, dc) in enumerate(((0, 1), (1, 0))):
            lo, mid, hi = (np.log(weights[r + k * dr, c + k * dc]) for k in (-1, 0, 1))
            curve = lo - 2.0 * mid + hi
            shift = 0.5 * (lo - hi) / curve
            ok &= np.isfinite(shift) & (curve < 0) & (np.abs(shift) <= 0.5)
            out[:, axis] = (c if axis == 0 else r) + np.where(np.isfinite(shift), shift, 0.0)
    return out, ok


def blob_centres(image: np.ndarray, level: float = 0.5, grow_px: float = 2.0, min_area: int = 1) -> np.ndarray:
    """Centres (N, 2) as (u, v) of the bright blobs of a 2-D image. Pixels above background +
    level·(peak − background) form blobs (8-connected, at least ``min_area`` pixels). A blob with a
    strict peak gets the three-point Gaussian fit of its peak; a flat-topped (saturated) one the
    background-subtracted intensity centroid over the blob grown by ``grow_px``."""
    img = np.asarray(image, dtype=np.float64)
    background = float(np.median(img))
    peak = float(img.max())
    if peak <= background:
        return np.empty((0, 2))
    labels, count = ndimage.label(img > background + level * (peak - background), structure=np.ones((3, 3)))
    if count == 0:
        return np.empty((0, 2))
    ids = np.arange(1, count + 1)
    areas = ndimage.sum_labels(np.ones_like(img), labels, ids)
    ids = ids[areas >= min_area]
    weights = np.clip(img - background, 0.0, None)
    # every pixel within grow_px of a blob joins the nearest blob, so neighbours never share pixels
    distance, (rows, cols) = ndimage.distance_transform_edt(labels == 0, return_indices=True)
    grown = np.where(distance <= grow_px, labels[rows, cols], 0)
    centroid = np.array(ndimage.center_of_mass(weights, grown, ids), dtype=np.float64).reshape(-1, 2)[:, ::-1]
    peaks = np.array(ndimage.maximum_position(weights, labels, ids), dtype=np.int64).reshape(-1, 2)
    fitted, ok = _gaussian_peaks(weights, peaks)
    return np.where(ok[:, None], fitted, centroid)


def frame_image(capture: psfmt.Capture, frame: int | None = None) -> np.ndarray:
    """The grey target image: one frame, or the mean of all frames (less noise)."""
    frames = capture.frames
    if frames is None or frames.count == 0:
        raise UserError(f"{capture.path or 'the capture'}: holds no frames of the LED target")
    if frame is not None and not -frames.count <= frame < frames.count:
        raise UserError(f"--frame {frame}: the capture has {frames.count} frames")
    stack = frames.as_float(slice(None) if frame is None else slice(frame % frames.count, frame % frames.count + 1))
    grey = stack.mean(axis=0)
    return grey.mean(axis=-1) if grey.ndim == 3 else grey


def event_image(capture: psfmt.Capture) -> np.ndarray:
    """Events per pixel over the whole capture, (H_e, W_e)."""
    events = capture.events
    if events is None or len(events) == 0:
        raise UserError(f"{capture.path or 'the capture'}: holds no events of the LED target")
    counts = np.zeros(events.height * events.width, dtype=np.int64)
    for block in events.chunks():
        counts += np.bincount(block.y.astype(np.int64) * events.width + block.x, minlength=counts.size)
    return counts.reshape(events.height, events.width).astype(np.float64)


def _triangles(points: np.ndarray, both_orders: bool) -> np.ndarray:
    """Index triples (i, a, b): each point with two of its nearest neighbours."""
    k = min(NEIGHBOURS, len(points) - 1)
    d = np.linalg.norm(points[:, None] - points[None], axis=-1)
    near = np.argsort(d, axis=1)[:, 1 : k + 1]
    pairs = np.array(list(combinations(range(k), 2)))
    if both_orders:
        pairs = np.vstack([pairs, pairs[:, ::-1]])
    i = np.repeat(np.arange(len(points)), len(pairs))
    return np.stack([i, near[i, np.tile(pairs[:, 0], len(points))], near[i, np.tile(pairs[:, 1], len(points))]], axis=1)


def _hypotheses(event_points: np.ndarray, frame_points: np.ndarray, prior: np.ndarray) -> np.ndarray:
    """Affines (H, 2, 3) mapping an event triangle onto a frame triangle, keeping those close to the
    prior's linear part (spectral norm of L·P⁻¹ − I below ``MAX_DEPARTURE``)."""
    te = _triangles(event_points, both_orders=False)
    tf = _triangles(frame_points, both_orders=True)
    eh = np.concatenate([event_points[te], np.ones((len(te), 3, 1))], axis=2)  # (Ne, 3, 3) rows (u, v, 1)
    good = np.abs(np.linalg.det(eh)) > 1e-6
    inv = np.linalg.inv(eh[good])  # A^T = inv(eh) @ f for the three points
    affines = np.einsum("eij,fjk->efki", inv, frame_points[tf]).reshape(-1, 2, 3)
    # the cameras share the view: keep maps within about 30° of rotation and 50 % of scale of the prior
    relative = affines[:, :, :2] @ np.linalg.inv(prior[:, :2])
    return affines[np.linalg.norm(relative - np.eye(2), ord=2, axis=(1, 2)) < MAX_DEPARTURE]


def match_affine(
    event_points: np.ndarray, frame_points: np.ndarray, prior: np.ndarray, tolerance_px: float | None = None
) -> AffineFit:
    """Robustly match LED centres of the two cameras and fit the event→frame affine (see the module
    docstring). ``tolerance_px`` (frame pixels) decides inliers; default a quarter of the median
    spacing of the frame blobs."""
    e = np.asarray(event_points, dtype=np.float64)
    f = np.asarray(frame_points, dtype=np.float64)
    if len(e) < 3 or len(f) < 3:
        raise UserError(f"calibration: found {len(f)} LED blob(s) in the frame and {len(e)} in the events; at least 3 each are needed (or give --pairs)")
    if tolerance_px is None:
        spacing = np.sort(np.linalg.norm(f[:, None] - f[None], axis=-1), axis=1)[:, 1]
        tolerance_px = 0.25 * float(np.median(spacing))
    candidates = _hypotheses(e, f, prior)
    if len(candidates) == 0:
        raise UserError("calibration: no LED triangles of the two cameras agree in scale with the prior; give --pairs")
    best: tuple[int, float] = (-1, np.inf)
    chosen = candidates[0]
    for start in range(0, len(candidates), _HYPOTHESIS_BLOCK):
        block = candidates[start : start + _HYPOTHESIS_BLOCK]
        mapped = np.einsum("hij,nj->hni", block[:, :, :2], e) + block[:, None, :, 2]
        nearest = np.linalg.norm(mapped[:, :, None] - f[None, None], axis=-1).min(axis=2)
        inliers = (nearest < tolerance_px).sum(axis=1)
        distance = np.linalg.norm((block - prior).reshape(len(block), -1), axis=1)
        order = np.lexsort((distance, -inliers))[0]
        if (inliers[order], -distance[order]) > (best[0], -best[1]):
            best = (int(inliers[order]), float(distance[order]))
            chosen = block[order]
    if best[0] < 3:
        raise UserError("calibration: fewer than 3 LED blobs of the two cameras could be matched; give --pairs")
    affine = chosen
    for _ in range(3):  # re-match with the refined map, mutual nearest neighbours within tolerance
        d = np.linalg.norm(apply_affine(affine, e)[:, None] - f[None], axis=-1)
        j = d.argmin(axis=1)
        mutual = (d.argmin(axis=0)[j] == np.arange(len(e))) & (d[np.arange(len(e)), j] < tolerance_px)
        fit = fit_affine(e[mutual], f[j[mutual]])
        affine = fit.affine
    return fit


def calibrate_target(
    capture: psfmt.Capture, *, frame: int | None = None, level: float = 0.5, tolerance_px: float | None = None
) -> AffineFit:
    """Detect the LEDs in the capture's frames and events and fit the event→frame affine. The prior
    is the affine of two cameras with the same field of view."""
    grey = frame_image(capture, frame)
    counts = event_image(capture)
    frame_points = blob_centres(grey, level)
    event_points = blob_centres(counts, level)
    assert capture.events is not None
    prior = default_affine(capture.events.width, grey.shape[1])
    fit = match_affine(event_points, frame_points, prior, tolerance_px)
    fit.frame_blobs, fit.event_blobs = len(frame_points), len(event_points)
    return fit


def read_pairs(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Manual correspondences: lines ``u_event v_event u_frame v_frame`` (``#`` starts a comment)."""
    try:
        rows = np.loadtxt(path, comments="#", ndmin=2)
    except (OSError, ValueError) as exc:
        raise UserError(f"{path}: cannot read point pairs ({str(exc).strip().splitlines()[0]})") from None
    if rows.ndim != 2 or rows.shape[1] != 4:
        raise UserError(f"{path}: expected lines of 'u_event v_event u_frame v_frame', got {rows.shape[1] if rows.ndim == 2 else 0} column(s)")
    return rows[:, :2], rows[:, 2:]


def store_affine(path: str | os.PathLike[str], affine: np.ndarray) -> None:
    """Set the event→frame affine in the capture at ``path``, rewriting it atomically (results,
    ground truth and everything else kept)."""
    capture = psfmt.read(path)
    try:
        capture.calibration.event_to_frame = np.asarray(affine, dtype=np.float64)
        psfmt.write(capture, path)
    finally:
        capture.close()
