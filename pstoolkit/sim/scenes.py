"""Synthetic scenes: geometry (normals, depth, mask) and materials (albedo, F0, roughness) on a square
frame grid, ready for the renderer.

A scene is a class with ``name``, ``summary`` and typed ``options`` and a method
``build(size, seed, **options) -> SceneMaps``; the core plugin registers ``SCENES`` and plugins may
register more. Depth is a height towards the camera in frame pixels, so cast shadows can be marched
in pixel units; normals are unit vectors in the camera frame (x right, y up, z towards the camera)
and agree with the depth (image row 0 is the top, so ∂h/∂y = −∂h/∂v).

    maps = get_registries().scenes.get("blobs").obj().build(128, seed=0, count=6)
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import cv2
import numpy as np

from pstoolkit.errors import UserError
from pstoolkit.io.normalmap import read_geometry_folder
from pstoolkit.plugin.options import Option

DIELECTRIC_F0 = 0.04
ALBEDO_MODES = ("white", "uniform", "texture")
RELIEF_IMAGES = ("camera", "coins", "moon", "text", "page", "clock")
# The random textures are drawn on this coarse grid and resized, so a seed gives the same pattern at
# every frame size.
_TEXTURE_GRID = 6


@dataclass
class SceneMaps:
    """What the renderer needs at frame resolution: ``normal`` (H, W, 3) float32 unit vectors,
    ``depth`` (H, W) float32 height towards the camera in pixels, ``mask`` (H, W) bool, ``albedo``
    (H, W, 3) and ``f0`` (H, W, 3) float32 in [0, 1], ``roughness`` (H, W) float32, ``metallic``
    (H, W) float32 (already folded into albedo and F0; kept as ground truth). Outside the mask every
    map is 0. ``self_shadowing`` False declares a surface that cannot cast a shadow on itself (a
    convex one, whose every point below a line of sight to the light faces away from it): the
    renderer then spends no time on cast shadows. ``mesh`` (optional) is the surface a scene was made
    from, ``(positions (N, 3) float32, faces (F, 3) uint32)`` in the camera frame in frame pixels
    (pixel (u, v) centred at x = u + ½ − W/2, y = H/2 − v − ½; z the height), which a renderer that
    draws meshes may draw instead of the height field (overhangs, the far side)."""

    normal: np.ndarray
    depth: np.ndarray
    mask: np.ndarray
    albedo: np.ndarray
    f0: np.ndarray
    roughness: np.ndarray
    metallic: np.ndarray
    self_shadowing: bool = True
    mesh: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def height(self) -> int:
        return int(self.mask.shape[0])

    @property
    def width(self) -> int:
        return int(self.mask.shape[1])

    def materials(self) -> dict[str, np.ndarray]:
        """The material maps stored as ground truth (``f0``, ``roughness``, ``metallic``)."""
        return {"f0": self.f0, "roughness": self.roughness, "metallic": self.metallic}


def material_options(
    albedo: str = "texture", f0: float = DIELECTRIC_F0, roughness: float = 0.4, metallic: float = 0.0
) -> tuple[Option, ...]:
    """The material options every built-in scene has, with scene-specific defaults."""
    return (
        Option("albedo", str, albedo, "diffuse colour: white, uniform (one random colour) or texture (smooth random RGB)", choices=ALBEDO_MODES),
        Option("f0", float, f0, "specular reflectance at normal incidence (grey) of the non-metallic part", minimum=0.0, maximum=1.0),
        Option("roughness", float, roughness, "GGX roughness", minimum=0.02, maximum=1.0),
        Option("varying", bool, False, "make F0 and roughness vary smoothly over the surface (×0.5 … ×1.5)"),
        Option("metallic", float, metallic, "metalness m: albedo → albedo·(1−m), F0 → lerp(F0, albedo, m)", minimum=0.0, maximum=1.0),
    )


def smooth_texture(rng: np.random.Generator, size: int, channels: int) -> np.ndarray:
    """A smooth random (size, size, channels) float32 field in [0, 1], the same pattern at every size."""
    coarse = rng.random((_TEXTURE_GRID, _TEXTURE_GRID, channels)).astype(np.float32)
    fine = cv2.resize(coarse, (size, size), interpolation=cv2.INTER_CUBIC).reshape(size, size, channels)
    return np.clip(fine, 0.0, 1.0)


def build_materials(mask: np.ndarray, rng: np.random.Generator, options: dict[str, Any]) -> dict[str, np.ndarray]:
    """Albedo, F0, roughness and metallic maps for ``mask`` from the material options."""
    h, w = mask.shape
    mode = options["albedo"]
    if mode == "white":
        albedo = np.full((h, w, 3), 0.8, np.float32)
    elif mode == "uniform":
        albedo = np.broadcast_to(rng.uniform(0.3, 0.9, 3).astype(np.float32), (h, w, 3)).copy()
    else:
        # a random base colour whose brightness and hue drift smoothly, like a painted object
        base = rng.uniform(0.45, 0.9, 3)
        field = smooth_texture(rng, max(h, w), 4)[:h, :w]
        # base · brightness · tint in float64, a channel at a time: 3× faster than broadcasting over
        # the (H, W, 3) array, the same values
        brightness = (0.55 + 0.45 * field[..., 0]).astype(np.float64)
        albedo = np.empty((h, w, 3), np.float32)
        for c in range(3):
            albedo[..., c] = base[c] * brightness * (0.8 + 0.2 * field[..., 1 + c])
    f0 = np.full((h, w), options["f0"], np.float32)
    roughness = np.full((h, w), options["roughness"], np.float32)
    if options["varying"]:
        variation = 0.5 + smooth_texture(rng, max(h, w), 2)[:h, :w]
        f0 = np.clip(f0 * variation[..., 0], 0.0, 1.0)
        roughness = np.clip(roughness * variation[..., 1], 0.02, 1.0)
    m = np.float32(options["metallic"])
    f0_rgb = (1.0 - m) * f0[..., None] + m * albedo
    albedo = albedo * (1.0 - m)
    inside = mask.astype(np.float32)
    return {
        "albedo": (albedo * inside[..., None]).astype(np.float32),
        "f0": (f0_rgb * inside[..., None]).astype(np.float32),
        "roughness": (roughness * inside).astype(np.float32),
        "metallic": (np.full((h, w), m, np.float32) * inside),
    }


def normals_from_height(height_px: np.ndarray) -> np.ndarray:
    """Unit normals (H, W, 3) of a height field in pixel units (central differences; one-sided at the
    border), camera frame: n ∝ (−∂h/∂u, +∂h/∂v, 1) because image v points down (−y)."""
    dh_dv, dh_du = np.gradient(height_px.astype(np.float64))
    n = np.stack([-dh_du, dh_dv, np.ones_like(dh_du)], axis=-1)
    return (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32)


def pixel_centres(size: int) -> tuple[np.ndarray, np.ndarray]:
    """The pixel centres of a size×size frame along its columns (x right) and its rows (y up, row 0
    the top), (size,) each, in units of the frame width: x, y ∈ (0, 1)."""
    c = (np.arange(size, dtype=np.float64) + 0.5) / size
    return c, 1.0 - c


def pixel_grid(size: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-centre coordinates (x right, y up) of a size×size frame in units of the frame width,
    x, y ∈ (0, 1) with (0.5, 0.5) the centre: ``pixel_centres`` on the (H, W) grid."""
    return np.meshgrid(*pixel_centres(size))


def assemble(
    normal: np.ndarray, depth: np.ndarray, mask: np.ndarray, materials: dict[str, np.ndarray], *,
    self_shadowing: bool = True,
) -> SceneMaps:
    """SceneMaps with geometry zeroed outside the mask and dtypes fixed."""
    mask = np.asarray(mask, bool)
    return SceneMaps(
        normal=(np.asarray(normal, np.float32) * mask[..., None]).astype(np.float32),
        depth=(np.asarray(depth, np.float32) * mask).astype(np.float32),
        mask=mask,
        **materials,
        self_shadowing=self_shadowing,
    )


class Scene(ABC):
    """A synthetic scene of the ``scenes`` registry: geometry and materials on a square frame.

    Subclasses set ``name``, ``summary`` and ``options`` and build the maps of one size."""

    name: ClassVar[str]
    summary: ClassVar[str]
    options: ClassVar[tuple[Option, ...]] = ()

    @abstractmethod
    def build(self, size: int, seed: int, **options: Any) -> SceneMaps:
        """The scene at ``size``×``size`` pixels; ``seed`` draws every random choice, ``options`` are
        the entry's options by name (defaults filled in)."""


class Sphere(Scene):
    """A sphere on a black background, seen from the top: every normal of the visible hemisphere
    (like DiLiGenT's ball), and no cast shadows: a convex surface shadows only where it faces away
    from the light, so it is built without self-shadowing."""

    name: ClassVar[str] = "sphere"
    summary: ClassVar[str] = "sphere on a black background (all normals of a hemisphere, no cast shadows)"
    options: ClassVar[tuple[Option, ...]] = (
        Option("radius", float, 0.9, "radius as a fraction of half the frame width", minimum=0.05, maximum=1.0),
        *material_options(),
    )

    def build(self, size: int, seed: int, **options: Any) -> SceneMaps:
        radius_px = options["radius"] * size / 2.0
        c = (size - 1) / 2.0
        v, u = np.mgrid[0:size, 0:size].astype(np.float64)
        x, y = (u - c) / radius_px, (c - v) / radius_px
        r2 = x * x + y * y
        mask = r2 < 1.0
        z = np.sqrt(np.clip(1.0 - r2, 0.0, None))
        normal = np.stack([x, y, z], axis=-1)
        materials = build_materials(mask, np.random.default_rng(seed), options)
        return assemble(normal, radius_px * z, mask, materials, self_shadowing=False)


class ChromeSphere(Sphere):
    """A polished metal sphere, the target that rigs calibrate their lights with: ``sphere`` with a
    low-roughness GGX lobe and no diffuse part (metallic 1), so each light shows as one small
    highlight at its mirror point (``pstoolkit calibrate lights``). Having no diffuse part, its frames
    take their automatic gain from the highlights' peak."""

    name: ClassVar[str] = "chrome-sphere"
    summary: ClassVar[str] = "mirror-like metal sphere (low-roughness GGX, no diffuse part) for light calibration"
    options: ClassVar[tuple[Option, ...]] = (
        Option("radius", float, 0.9, "radius as a fraction of half the frame width", minimum=0.05, maximum=1.0),
        *material_options(albedo="white", f0=DIELECTRIC_F0, roughness=0.25, metallic=1.0),
    )


class Blobs(Scene):
    """Smooth Gaussian bumps of random height and width on a flat base that fills the frame: a
    non-convex surface whose steep bumps cast long shadows onto the base and onto each other."""

    name: ClassVar[str] = "blobs"
    summary: ClassVar[str] = "Gaussian bumps on a plane: smooth, non-convex, strong cast shadows"
    options: ClassVar[tuple[Option, ...]] = (
        Option("count", int, 7, "number of bumps", minimum=1, maximum=64),
        Option("height", float, 0.2, "tallest bump height as a fraction of the frame width", minimum=0.0, maximum=1.0),
        *material_options(),
    )

    def build(self, size: int, seed: int, **options: Any) -> SceneMaps:
        rng = np.random.default_rng(seed)
        count = options["count"]
        centres = rng.uniform(0.2, 0.8, (count, 2))
        heights = options["height"] * rng.uniform(0.4, 1.0, count)
        widths = rng.uniform(0.06, 0.12, count)
        # h and its gradient in units of the frame width (the slope is then the same in pixel units),
        # at the pixel centres; a bump is a product of Gaussians along x and y, so the sums over bumps
        # are (B, H)ᵀ @ (B, W) products (heights and normals at 256²: 1.9 ms, against 5.3 for a bump
        # at a time over the whole grid)
        x, y = pixel_centres(size)
        dx = x[None, :] - centres[:, :1]
        dy = y[None, :] - centres[:, 1:]
        s2 = (widths * widths)[:, None]
        along_x = np.exp(-dx * dx / (2.0 * s2))
        along_y = heights[:, None] * np.exp(-dy * dy / (2.0 * s2))
        h = along_y.T @ along_x
        dh_dx = -(along_y.T @ (along_x * dx / s2))
        dh_dy = -((along_y * dy / s2).T @ along_x)
        # (−∂h/∂x, −∂h/∂y, 1) / its length, without (H, W, 3) temporaries
        inverse = 1.0 / np.sqrt(dh_dx * dh_dx + dh_dy * dh_dy + 1.0)
        normal = np.empty((size, size, 3), np.float32)
        normal[..., 0] = -dh_dx * inverse
        normal[..., 1] = -dh_dy * inverse
        normal[..., 2] = inverse
        mask = np.ones((size, size), bool)
        materials = build_materials(mask, rng, options)
        return assemble(normal, h * size, mask, materials)


def relief_image(name: str) -> np.ndarray:
    """A grey scikit-image sample image as float64 in [0, 1]."""
    from skimage import data

    image = np.asarray(getattr(data, name)(), dtype=np.float64)
    if image.ndim == 3:
        image = image[..., :3] @ np.array([0.299, 0.587, 0.114])
    return (image - image.min()) / max(float(np.ptp(image)), 1e-12)


class Relief(Scene):
    """A near-planar bas-relief on a round plate, its height a smoothed scikit-image sample image
    (in the manner of DiLiGenT-Π's reliefs)."""

    name: ClassVar[str] = "relief"
    summary: ClassVar[str] = "near-planar bas-relief on a round plate, carved from a scikit-image sample image"
    options: ClassVar[tuple[Option, ...]] = (
        Option("image", str, "coins", "scikit-image sample image for the height", choices=RELIEF_IMAGES),
        Option("height", float, 0.03, "relief height as a fraction of the frame width", minimum=0.0, maximum=0.5),
        Option("smooth", float, 1.5, "Gaussian blur of the image in frame pixels per 128 pixels", minimum=0.0),
        *material_options(albedo="uniform", f0=0.2, roughness=0.3, metallic=0.0),
    )

    def build(self, size: int, seed: int, **options: Any) -> SceneMaps:
        image = relief_image(options["image"])
        side = min(image.shape)
        top, left = (image.shape[0] - side) // 2, (image.shape[1] - side) // 2
        square = np.ascontiguousarray(image[top : top + side, left : left + side])
        small = cv2.resize(square, (size, size), interpolation=cv2.INTER_AREA)
        sigma = options["smooth"] * size / 128.0
        if sigma > 0:
            small = cv2.GaussianBlur(small, (0, 0), sigma)
        height = options["height"] * size * small
        x, y = pixel_grid(size)
        mask = (x - 0.5) ** 2 + (y - 0.5) ** 2 < 0.47**2
        materials = build_materials(mask, np.random.default_rng(seed), options)
        return assemble(normals_from_height(height), height, mask, materials)


class Geometry(Scene):
    """A real shape from a folder: ``normal_map.png`` (16-bit, n = v/65535·2 − 1, camera frame x right,
    y up, z to the camera), ``depth_gt.npz`` (key ``depth_gt``, distance from the camera in mm) and
    ``mask.png``, plus ``K.txt`` (3×3 intrinsics) to turn the depth into pixel units: a depth step of
    d mm at the mean depth Z̄ spans d·f/Z̄ pixels, with f the mean of fx and fy. The shape is cropped to
    a square around the mask (8 % margin) and resized to the frame size."""

    name: ClassVar[str] = "geometry"
    summary: ClassVar[str] = "a real shape from a folder with normal_map.png, depth_gt.npz, mask.png and K.txt"
    options: ClassVar[tuple[Option, ...]] = (
        Option("source", str, "", "folder with normal_map.png, depth_gt.npz, mask.png and K.txt"),
        *material_options(),
    )

    def build(self, size: int, seed: int, **options: Any) -> SceneMaps:
        if not options["source"]:
            raise UserError("needs a source folder (--source DIR)")
        normal, height_px, mask = read_geometry(Path(options["source"]))
        normal, height_px, mask = crop_resize(normal, height_px, mask, size)
        materials = build_materials(mask, np.random.default_rng(seed), options)
        return assemble(normal, height_px, mask, materials)


def read_geometry(folder: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normals (H, W, 3), height towards the camera in pixels (H, W) and mask (H, W) of a geometry
    folder (layout in ``Geometry``)."""
    normal, mask, depth_mm = read_geometry_folder(folder)
    k_path = folder / "K.txt"
    if not k_path.is_file():
        raise UserError(f"{k_path}: file does not exist (the intrinsics turn depth_gt in mm into pixels)")
    try:
        k = np.loadtxt(k_path, dtype=np.float64).reshape(3, 3)
    except ValueError:
        raise UserError(f"{k_path}: expected a 3×3 matrix of numbers") from None
    mask = mask & np.isfinite(depth_mm) & (depth_mm > 0)
    if not mask.any():
        raise UserError(f"{folder}: the mask holds no pixel with a valid depth")
    mean_mm = float(depth_mm[mask].mean())
    focal_px = 0.5 * (k[0, 0] + k[1, 1])
    height_px = np.where(mask, (mean_mm - depth_mm) * focal_px / mean_mm, 0.0)
    return normal, height_px, mask


def crop_resize(
    normal: np.ndarray, height_px: np.ndarray, mask: np.ndarray, size: int, margin: float = 0.08
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Crop a square around the mask (``margin`` of its side on each side, padded with background
    where the square leaves the image) and resize to size×size. Heights scale with the image so
    they stay in pixel units; normals are area-averaged and re-normalised."""
    rows, cols = np.nonzero(mask)
    cy, cx = (rows.min() + rows.max()) / 2.0, (cols.min() + cols.max()) / 2.0
    side = int(np.ceil(max(np.ptp(rows), np.ptp(cols)) + 1) * (1.0 + 2.0 * margin))
    top, left = int(round(cy - side / 2.0)), int(round(cx - side / 2.0))
    pad = side

    def crop(a: np.ndarray) -> np.ndarray:
        widths = ((pad, pad), (pad, pad)) + ((0, 0),) * (a.ndim - 2)
        return np.pad(a, widths)[top + pad : top + pad + side, left + pad : left + pad + side]

    m = crop(mask.astype(np.float32))
    weight = cv2.resize(m, (size, size), interpolation=cv2.INTER_AREA)
    small_mask = weight > 0.5
    safe = np.maximum(weight, 1e-6)
    n = cv2.resize(crop(normal * mask[..., None]).astype(np.float32), (size, size), interpolation=cv2.INTER_AREA)
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    h = cv2.resize(crop(height_px * mask).astype(np.float32), (size, size), interpolation=cv2.INTER_AREA) / safe
    h *= size / side
    return n, np.where(small_mask, h, 0.0), small_mask


class Hollows(Scene):
    """Two tall rounded ridges with a deep, narrow valley between them, on a round plate: the
    valley's floor is in cast shadow for most of a turn of a 45° ring light and lit mostly by what
    the ridges' walls reflect (a path tracer's inter-reflection) — the case a shadow model is for."""

    name: ClassVar[str] = "hollows"
    summary: ClassVar[str] = "two ridges with a deep narrow valley between: long cast shadows, strong inter-reflection"
    options: ClassVar[tuple[Option, ...]] = (
        Option("height", float, 0.3, "ridge height as a fraction of the frame width", minimum=0.0, maximum=1.0),
        Option("gap", float, 0.1, "distance between the ridges' crests as a fraction of the frame width", minimum=0.02, maximum=0.5),
        *material_options(),
    )

    def build(self, size: int, seed: int, **options: Any) -> SceneMaps:
        x, y = pixel_grid(size)
        half_gap, width = options["gap"] / 2.0, options["gap"] / 2.5
        bend = 0.06 * np.sin(2.0 * np.pi * (y - 0.5))
        along = np.exp(-((y - 0.5) ** 2) / (2.0 * 0.22**2))
        ridges = sum(np.exp(-((x - 0.5 - bend - side * half_gap) ** 2) / (2.0 * width**2)) for side in (-1.0, 1.0))
        height = options["height"] * size * along * ridges
        mask = (x - 0.5) ** 2 + (y - 0.5) ** 2 < 0.47**2
        materials = build_materials(mask, np.random.default_rng(seed), options)
        return assemble(normals_from_height(height), height, mask, materials)


class Pits(Scene):
    """Deep smooth pits sunk into a round plate (random positions, depths twice to three times their
    radius): their floors see the light for a small part of a turn and each other's walls all the time."""

    name: ClassVar[str] = "pits"
    summary: ClassVar[str] = "deep smooth pits in a plate: floors in cast shadow most of a turn"
    options: ClassVar[tuple[Option, ...]] = (
        Option("count", int, 5, "number of pits", minimum=1, maximum=32),
        Option("depth", float, 2.5, "pit depth in units of its radius", minimum=0.0, maximum=10.0),
        *material_options(),
    )

    def build(self, size: int, seed: int, **options: Any) -> SceneMaps:
        rng = np.random.default_rng(seed)
        count = options["count"]
        angle = rng.uniform(0.0, 2.0 * np.pi, count)
        reach = np.sqrt(rng.uniform(0.0, 1.0, count)) * 0.28
        centres = 0.5 + reach[:, None] * np.stack([np.cos(angle), np.sin(angle)], axis=1)
        radii = rng.uniform(0.05, 0.08, count)
        x, y = pixel_grid(size)
        height = np.zeros((size, size))
        for (cx, cy), r in zip(centres, radii):
            # a smooth well: flat at the plate, steepest at r/√2, its floor 'depth'·r below
            height -= options["depth"] * r * size * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (r * r))
        mask = (x - 0.5) ** 2 + (y - 0.5) ** 2 < 0.47**2
        materials = build_materials(mask, np.random.default_rng(seed + 1), options)
        return assemble(normals_from_height(height), height - height.min(), mask, materials)


SCENES: tuple[type[Scene], ...] = (Sphere, ChromeSphere, Blobs, Relief, Geometry, Hollows, Pits)
