"""A calibration sphere in an image: where it is, and the normal, view and mirror direction at a pixel.

The sphere is found as a circle in frame pixels (``Circle``: from a mask or silhouette, or given by
the user as ``cx,cy,r``). Through an orthographic camera the circle is the sphere's outline; through
a pinhole camera (``intrinsics`` K, ``psfmt.camera``) the outline is the base of the cone of rays
tangent to the sphere, whose axis and half-angle fix the sphere up to scale (its centre is put at
distance 1 from the camera: directions do not depend on the scale).

    circle, outline = circle_from_mask(mask, "mask.png")  # or parse_circle("31.5,31.5,28"), None
    sphere = SphereView.build(circle, intrinsics, outline)  # orthographic when intrinsics is None
    n, v = sphere.normals(u, v)                           # (N, 3) each, camera frame
    l = reflect(n, v)                                     # mirror direction towards the light

Frame conventions: pixel (u, v) is column u and row v with centres at integers; the camera frame is
x right, y up, z towards the camera.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from psfmt.camera import intrinsics_problem, pixel_rays
from pstoolkit.errors import UserError

MIN_OUTLINE_POINTS = 8


@dataclass(frozen=True)
class Circle:
    """A circle in frame pixels: centre (cx, cy) and radius r."""

    cx: float
    cy: float
    r: float


def parse_circle(text: str, what: str = "--sphere") -> Circle:
    """``"cx,cy,r"`` (frame pixels) → Circle; UserError naming ``what`` for anything else."""
    parts = text.replace(" ", "").split(",")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) != 3 or not all(np.isfinite(values)) or values[2] <= 0:
        raise UserError(f"{what} {text[:40]!r}: expected cx,cy,r in frame pixels with r > 0")
    return Circle(*values)


def outline_points(mask: np.ndarray) -> np.ndarray:
    """(N, 2) points (u, v) on the outline of a binary mask: the midpoint of every pair of
    4-neighbouring pixels of which one is inside and one outside."""
    m = np.asarray(mask, dtype=bool)
    rows, cols = np.nonzero(m[:, 1:] != m[:, :-1])
    horizontal = np.stack([cols + 0.5, rows.astype(np.float64)], axis=1)
    rows, cols = np.nonzero(m[1:, :] != m[:-1, :])
    vertical = np.stack([cols.astype(np.float64), rows + 0.5], axis=1)
    return np.vstack([horizontal, vertical])


def fit_circle(points: np.ndarray, what: str) -> Circle:
    """Least-squares (Kåsa) circle through (N, 2) points; UserError naming ``what`` when there are
    too few or they do not span a circle."""
    p = np.asarray(points, dtype=np.float64)
    if len(p) < MIN_OUTLINE_POINTS:
        raise UserError(f"{what}: the sphere's outline has {len(p)} points, too few to fit a circle (give --sphere cx,cy,r)")
    centre = p.mean(axis=0)
    q = p - centre
    design = np.hstack([q, np.ones((len(q), 1))])
    rhs = (q * q).sum(axis=1)
    solution, *_ = np.linalg.lstsq(design, rhs, rcond=None)
    a, b, c = solution
    r2 = c + 0.25 * (a * a + b * b)
    if not np.isfinite(r2) or r2 <= 1.0:
        raise UserError(f"{what}: the outline is not a circle (give --sphere cx,cy,r)")
    return Circle(float(centre[0] + 0.5 * a), float(centre[1] + 0.5 * b), float(np.sqrt(r2)))


def largest_region(mask: np.ndarray) -> np.ndarray:
    """The largest 8-connected region of a binary mask, holes filled."""
    from scipy import ndimage  # deferred: scipy is needed only here

    labels, count = ndimage.label(mask, structure=np.ones((3, 3)))
    if count == 0:
        return np.zeros_like(mask, dtype=bool)
    sizes = np.bincount(labels.ravel())[1:]
    return ndimage.binary_fill_holes(labels == 1 + int(sizes.argmax()))


def circle_from_mask(mask: np.ndarray, what: str) -> tuple[Circle, np.ndarray]:
    """The circle through the outline of the largest region of ``mask`` (H, W), and the outline's
    points (N, 2)."""
    points = outline_points(largest_region(np.asarray(mask, dtype=bool)))
    return fit_circle(points, what), points


def circle_from_image(image: np.ndarray, level: float, what: str) -> tuple[Circle, np.ndarray]:
    """The sphere's silhouette in a grey (H, W) image (the brightest of all views, say): pixels above
    ``level`` of the way from the median to the peak, largest region, circle through its outline
    (and the outline's points)."""
    img = np.asarray(image, dtype=np.float64)
    background, peak = float(np.median(img)), float(img.max())
    if not peak > background:
        raise UserError(f"{what}: the images are blank, no sphere to find (give --sphere cx,cy,r)")
    return circle_from_mask(img > background + level * (peak - background), what)


def reflect(n: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Mirror direction 2(n·v)n − v of unit view directions ``v`` about unit normals ``n`` (..., 3)."""
    return 2.0 * np.sum(n * v, axis=-1, keepdims=True) * n - v


def unit_rows(x: np.ndarray) -> np.ndarray:
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


@dataclass(frozen=True)
class SphereView:
    """A sphere seen by the camera: ``circle`` in frame pixels and, for a pinhole camera,
    ``intrinsics`` (3, 3), the unit ``axis`` from the camera to the sphere's centre and
    ``sin_half`` (the sine of the half-angle of the tangent cone: the radius at distance 1)."""

    circle: Circle
    intrinsics: np.ndarray | None = None
    axis: np.ndarray | None = None
    sin_half: float = 0.0

    @classmethod
    def build(cls, circle: Circle, intrinsics: np.ndarray | None = None, outline: np.ndarray | None = None) -> SphereView:
        """The sphere of outline ``circle``; with ``intrinsics`` the tangent cone is fitted (axis a,
        half-angle θ: every outline ray b has b·a = cos θ) through the ``outline`` points (N, 2) when
        given (a pinhole camera sees the sphere as an ellipse, which the circle only approximates),
        else through 64 points of the circle."""
        if intrinsics is None:
            return cls(circle)
        k = np.asarray(intrinsics, dtype=np.float64)
        problem = intrinsics_problem(k)
        if problem is not None:
            raise UserError(f"intrinsics {problem}")
        if outline is None:
            angle = np.linspace(0.0, 2.0 * np.pi, 64, endpoint=False)
            outline = np.stack([circle.cx + circle.r * np.cos(angle), circle.cy + circle.r * np.sin(angle)], axis=1)
        rays = unit_rows(pixel_rays(k, outline[:, 0], outline[:, 1]))
        w, *_ = np.linalg.lstsq(rays, np.ones(len(rays)), rcond=None)
        cos_half = 1.0 / float(np.linalg.norm(w))
        return cls(circle, k, w * cos_half, float(np.sqrt(max(0.0, 1.0 - cos_half * cos_half))))

    def normals(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Unit normals (N, 3) and unit directions towards the camera (N, 3) at pixels (u, v) (N,),
        and ``on`` (N,) bool, False where the pixel's ray misses the sphere (its normal is then the
        one at the nearest point of the outline)."""
        u = np.asarray(u, dtype=np.float64).ravel()
        v = np.asarray(v, dtype=np.float64).ravel()
        c = self.circle
        if self.intrinsics is None:
            x, y = (u - c.cx) / c.r, (c.cy - v) / c.r
            r2 = x * x + y * y
            on = r2 < 1.0
            z = np.sqrt(np.clip(1.0 - r2, 0.0, None))
            n = unit_rows(np.stack([x, y, z], axis=-1))
            return n, np.broadcast_to(np.array([0.0, 0.0, 1.0]), n.shape).copy(), on
        assert self.axis is not None
        d = unit_rows(pixel_rays(self.intrinsics, u, v))
        along = d @ self.axis
        disc = along * along - 1.0 + self.sin_half**2
        on = disc > 0
        t = along - np.sqrt(np.clip(disc, 0.0, None))
        n = unit_rows(t[:, None] * d - self.axis)
        return n, -d, on
