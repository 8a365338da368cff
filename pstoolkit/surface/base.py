"""The normal-integration contract: the pinhole ``Camera``, the ``Surface`` an integrator returns, the
base class ``Integrator`` registered through ``pstoolkit_register_integrators``, and ``points``, the
3-D point of each pixel of a surface (for meshes).

    class Mine(Integrator):
        name = "mine"
        summary = "least squares with a smoothness prior"
        options = (Option("smoothness", float, 0.1, "weight of the prior"),)

        def integrate(self, normal, mask, options, camera=None):
            normal, mask = checked_inputs(normal, mask)
            ...
            return Surface(depth, mask, "orthographic" if camera is None else "perspective", seconds)

Frames and units. Pixels are (u, v): u the column, v the row (growing downwards), pixel centres at
integers. The camera frame has x right, y up and z towards the camera, so larger z is nearer, and
normals (H, W, 3) are unit vectors in it, facing the camera.

- Orthographic (``camera`` None): ``depth`` is z in frame pixels (one pixel across = one unit of
  depth), with an arbitrary offset per connected part of the mask (each part's mean is near 0).
- Perspective (a ``Camera``): the pinhole sits at the origin and looks along −z, so a visible point
  has z < 0: ``depth`` is z = −d, d > 0 its distance along the optical axis. Normals fix a
  perspective surface only up to a global scale (a surface twice as large and twice as far has the
  same normals), so the integrators choose the scale that puts the median d of the mask at
  f = (fx + fy)/2: there one pixel spans one unit sideways, the unit of the orthographic case.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal

import numpy as np

from pstoolkit._shared.vectors import solved_pixels
from pstoolkit.plugin.options import Option

Projection = Literal["orthographic", "perspective"]


@dataclass(frozen=True)
class Camera:
    """Pinhole intrinsics in frame pixels: focal lengths ``fx``, ``fy`` and the principal point
    (``cx``, ``cy``), with pixel centres at integers and v down (the layout of an OpenCV or
    DiLiGenT ``K``). Raises ValueError unless the focal lengths are positive and all four finite."""

    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        if not all(math.isfinite(value) for value in (self.fx, self.fy, self.cx, self.cy)):
            raise ValueError(f"camera intrinsics must be finite, got {self}")
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"camera focal lengths must be positive, got fx={self.fx}, fy={self.fy}")

    @classmethod
    def from_matrix(cls, k: np.ndarray) -> Camera:
        """The camera of a 3×3 intrinsic matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]] (skew ignored)."""
        k = np.asarray(k, dtype=np.float64)
        if k.shape != (3, 3):
            raise ValueError(f"an intrinsic matrix is 3×3, got shape {k.shape}")
        return cls(fx=float(k[0, 0]), fy=float(k[1, 1]), cx=float(k[0, 2]), cy=float(k[1, 2]))

    @property
    def focal(self) -> float:
        """(fx + fy)/2: the distance at which one pixel spans one unit (the perspective depth scale)."""
        return 0.5 * (self.fx + self.fy)

    def rays(self, shape: tuple[int, int]) -> np.ndarray:
        """(H, W, 3) float64 ray of each pixel scaled to unit distance along the axis:
        ((u − cx)/fx, −(v − cy)/fy, −1), so the pixel's point at distance d is d·ray."""
        height, width = shape
        v, u = np.mgrid[0:height, 0:width].astype(np.float64)
        return np.stack([(u - self.cx) / self.fx, -(v - self.cy) / self.fy, -np.ones_like(u)], axis=-1)


@dataclass
class Surface:
    """An integrated surface.

    ``depth`` (H, W) float64: z in the camera frame (larger is nearer), NaN outside ``mask``; frame
    pixels for an orthographic surface, for a perspective one z = −d (d the distance along the axis)
    up to a global scale (module docstring). ``mask`` (H, W) bool: the pixels with a depth.
    ``projection``: "orthographic" or "perspective". ``seconds``: wall-clock time of the integration.
    ``diagnostics``: what the integrator reports about its run (iterations, final energy …)."""

    depth: np.ndarray
    mask: np.ndarray
    projection: Projection
    seconds: float
    diagnostics: dict[str, Any] = field(default_factory=dict)


class Integrator(ABC):
    """A normal-integration method: ``name`` (registry name), ``summary`` (one line), typed
    ``options``. ``integrate`` turns a normal map into a ``Surface``, orthographic when ``camera`` is
    None, through the camera otherwise."""

    name: ClassVar[str]
    summary: ClassVar[str]
    options: ClassVar[tuple[Option, ...]] = ()

    @abstractmethod
    def integrate(self, normal: np.ndarray, mask: np.ndarray, options: dict[str, Any], camera: Camera | None = None) -> Surface:
        """The surface of unit ``normal`` (H, W, 3) over ``mask`` (H, W) bool, with the full
        ``options`` dict (defaults filled in). Raises ValueError on mismatched shapes or on mask
        pixels without a usable normal."""


def checked_inputs(normal: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(normal (H, W, 3) float64 renormalised to unit length, mask (H, W) bool), or ValueError when
    the shapes disagree or a pixel of the mask is not solved (``solved_pixels``: a zero, tiny or
    non-finite normal; leave those out of the mask: an unsolved pixel has no slope to integrate)."""
    normal = np.asarray(normal, dtype=np.float64)
    mask = np.asarray(mask)
    if mask.ndim != 2:
        raise ValueError(f"mask must be (H, W), got shape {mask.shape}")
    if normal.shape != (*mask.shape, 3):
        raise ValueError(f"normal map of shape {normal.shape} does not fit mask of shape {mask.shape} (expected {(*mask.shape, 3)})")
    mask = mask.astype(bool)
    bad = mask & ~solved_pixels(normal)
    if bad.any():
        raise ValueError(f"{int(bad.sum())} pixels of the mask have a zero or non-finite normal; leave them out of the mask")
    length = np.linalg.norm(normal, axis=-1)
    unit = np.zeros_like(normal)
    unit[mask] = normal[mask] / length[mask][:, None]
    return unit, mask


def points(surface: Surface, camera: Camera | None = None) -> np.ndarray:
    """(H, W, 3) float64 point (x, y, z) of each pixel of ``surface`` in the camera frame, NaN
    outside its mask. An orthographic surface (``camera`` is then not needed, and ignored):
    x = u − (W−1)/2, y = (H−1)/2 − v in pixels, z = depth. A perspective one: the pixel's ray through
    ``camera`` at distance d = −depth along the axis, x = (u − cx)/fx·d, y = −(v − cy)/fy·d,
    z = depth. Raises ValueError when a perspective surface comes without its camera."""
    depth = np.where(surface.mask, np.asarray(surface.depth, dtype=np.float64), np.nan)
    height, width = depth.shape
    if surface.projection == "perspective" and camera is None:
        raise ValueError("a perspective surface needs its camera to place its points")
    if surface.projection == "orthographic":
        v, u = np.mgrid[0:height, 0:width].astype(np.float64)
        xy = np.stack([u - (width - 1) / 2, (height - 1) / 2 - v], axis=-1)
        out = np.concatenate([xy, depth[..., None]], axis=-1)
    else:
        assert camera is not None
        out = camera.rays(depth.shape) * (-depth)[..., None]
    out[~surface.mask] = np.nan
    return out
