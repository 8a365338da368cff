"""The ``mesh`` scene: a mesh file seen from above, for the ``mitsuba`` renderer.

The mesh (PLY, OBJ, STL, OFF, GLB: what trimesh reads) is taken in the camera frame (x right, y up,
z towards the camera), centred on the frame, scaled so its larger side across the image spans
``fill`` of the frame, and lifted so its lowest point is at z = 0. Mitsuba rasterises it through the
renderer's camera (``pstoolkit_mitsuba.shapes``) into the maps every scene has: per pixel the mean
shading normal over the pixel's footprint (Mitsuba's area-weighted vertex normals), renormalised,
and the mean height, kept where the surface covers the pixel wholly (every one of ``RASTER_SPP``
samples hits). The ``mitsuba`` renderer draws the mesh itself (``SceneMaps.mesh``), with its
overhangs and hidden sides; the own renderer sees the height field of the maps.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from pstoolkit import Option, UserError
from pstoolkit.sim.scenes import Scene, SceneMaps, assemble, build_materials, material_options
from pstoolkit_mitsuba.shapes import CAMERA_HEIGHT_PX, orthographic_sensor, planar_texcoords, triangle_mesh
from pstoolkit_mitsuba.variants import AUTO, set_variant

RASTER_SPP = 64
MAX_MESH_BYTES = 1 << 30
"""Largest mesh file read: a bigger one is refused before it is loaded."""


def read_mesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (N, 3) float64 and faces (F, 3) int64 of a mesh file; UserError naming the file when it
    is missing, too big, unreadable or without triangles."""
    import trimesh

    if not path.is_file():
        raise UserError(f"{path}: file does not exist")
    size = path.stat().st_size
    if size > MAX_MESH_BYTES:
        raise UserError(f"{path}: {size:,} bytes, more than the {MAX_MESH_BYTES:,} a mesh may have")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh reports a malformed file through many exception types
        raise UserError(f"{path}: not a readable mesh ({type(exc).__name__})") from None
    vertices, faces = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)
    if faces.ndim != 2 or faces.shape[1:] != (3,) or not len(faces) or not np.all(np.isfinite(vertices)):
        raise UserError(f"{path}: holds no triangles with finite vertices")
    return vertices, faces


def place(vertices: np.ndarray, size: int, fill: float) -> np.ndarray:
    """(N, 3) float32: ``vertices`` centred on the frame across the image, scaled so the larger of
    their x and y extents spans ``fill``·``size`` pixels, lowest z at 0."""
    low, high = vertices.min(axis=0), vertices.max(axis=0)
    extent = float(max(high[0] - low[0], high[1] - low[1]))
    if not extent > 0:
        raise UserError("the mesh has no extent across the image (x and y)")
    scale = fill * size / extent
    centre = np.array([(low[0] + high[0]) / 2.0, (low[1] + high[1]) / 2.0, low[2]])
    return ((vertices - centre) * scale).astype(np.float32)


def rasterise(positions: np.ndarray, faces: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normals (H, W, 3), heights (H, W) in pixels and the mask (H, W) of wholly covered pixels of
    the placed mesh (module docstring)."""
    mi = set_variant(AUTO)
    shape = triangle_mesh(mi, positions, faces.astype(np.uint32), planar_texcoords(positions, size, size))
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "aov", "aovs": "nn:sh_normal,dd:depth", "inner": {"type": "direct"}},
        "sensor": orthographic_sensor(mi, size, size, RASTER_SPP, pixel_format="rgba"),
        "surface": shape,
    })
    image = np.asarray(mi.render(scene, seed=0), dtype=np.float64)
    alpha, normal, depth = image[..., 3], image[..., 4:7], image[..., 7]
    length = np.linalg.norm(normal, axis=-1)
    mask = (alpha > 1.0 - 0.5 / RASTER_SPP) & (length > 1e-6)
    normal = np.where(mask[..., None], normal / np.maximum(length, 1e-12)[..., None], 0.0)
    return normal, np.where(mask, CAMERA_HEIGHT_PX - depth, 0.0), mask


class MeshScene(Scene):
    """A mesh file seen from above (module docstring); needs the ``mitsuba`` extra."""

    name: ClassVar[str] = "mesh"
    summary: ClassVar[str] = "a mesh file (PLY, OBJ, STL …) seen from +z, rasterised by Mitsuba (pip install 'pstoolkit[mitsuba]')"
    options: ClassVar[tuple[Option, ...]] = (
        Option("source", str, "", "mesh file, in the camera frame (x right, y up, z towards the camera)"),
        Option("fill", float, 0.9, "share of the frame the mesh's larger side across the image spans", minimum=0.05, maximum=1.0),
        *material_options(),
    )

    def build(self, size: int, seed: int, **options: Any) -> SceneMaps:
        if not options["source"]:
            raise UserError("needs a mesh file (--source FILE)")
        vertices, faces = read_mesh(Path(options["source"]))
        positions = place(vertices, size, options["fill"])
        normal, height, mask = rasterise(positions, faces, size)
        if not mask.any():
            raise UserError(f"{options['source']}: the mesh covers no whole pixel at {size}×{size}")
        materials = build_materials(mask, np.random.default_rng(seed), options)
        return replace(assemble(normal, height, mask, materials), mesh=(positions, faces.astype(np.uint32)))
