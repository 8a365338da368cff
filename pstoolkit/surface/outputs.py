"""What ``pstoolkit run --integrate NAME`` and ``pstoolkit integrate RESULT_DIR`` add to a result
folder: the surface a registered integrator makes of the normal map, as

- ``depth.npy``: float32 (H, W), z of the surface towards the camera (``Surface.depth``), NaN outside
  the integrated pixels;
- ``depth.png``: 16-bit grey, pixel = 1 + round((z − offset) / scale · 65534), 0 outside, so
  z = offset + (pixel − 1) / 65534 · scale (``offset`` and ``scale`` in ``result.json``; nearer is brighter);
- ``mesh.ply`` (binary) and ``mesh.obj``: one vertex per integrated pixel at its 3-D point
  (``pstoolkit.surface.base.points``), two triangles per 2×2 block of pixels (each where its three
  pixels are integrated), facing the camera; the albedo, when the solver wrote one, as vertex
  colours. Written through trimesh.

and, in ``result.json``, a ``surface`` entry: the integrator, its options, the projection, seconds,
the files and — when the capture has ground-truth depth — the depth error after the least-squares
scale and offset alignment (``pstoolkit.evaluation.metrics.depth_error``): RMSE in the truth's units
and as a share of the truth's depth range over the mask. Files are written first and ``result.json``
last, each atomically, so a folder's ``result.json`` lists only files that exist.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

import psfmt
from pstoolkit._shared.vectors import solved_pixels
from pstoolkit.errors import UserError
from pstoolkit.evaluation.metrics import depth_error
from pstoolkit.evaluation.scoring import RESULT_FILE, read_result_json
from pstoolkit.io.normalmap import read_normal_npy, read_npy, write_npy, write_png
from pstoolkit.io.textdata import summary_json
from pstoolkit.plugin.registry import Entry
from pstoolkit.surface.base import Camera, Surface, points

DEPTH_NPY, DEPTH_PNG, MESH_PLY, MESH_OBJ = "depth.npy", "depth.png", "mesh.ply", "mesh.obj"
PNG_LEVELS = 65534


@dataclass
class SurfaceInputs:
    """What integration reads: ``normal`` (H, W, 3) float32 unit normals (zero outside ``mask``
    (H, W) bool), the solver's ``albedo`` (H, W, 3) when it wrote one, the capture's ground-truth
    ``truth_depth`` (H, W) and its ``camera`` when known."""

    normal: np.ndarray
    mask: np.ndarray
    albedo: np.ndarray | None = None
    truth_depth: np.ndarray | None = None
    camera: Camera | None = None


def capture_truth(capture: Path, shape: tuple[int, int]) -> tuple[np.ndarray | None, Camera | None]:
    """The ground-truth depth (None without, or when its size is not ``shape``) and the camera
    (None: orthographic) of ``capture``."""
    with psfmt.read(capture, verify=True) as data:
        truth = data.ground_truth
        depth = None if truth is None or truth.depth is None else np.asarray(truth.depth, dtype=np.float64)
        camera = camera_of(data.calibration)
    if depth is not None and depth.shape != shape:
        depth = None
    return depth, camera


def camera_of(calibration: psfmt.Calibration | None) -> Camera | None:
    """The pinhole camera of a capture's calibration (format 1.2 ``intrinsics``), None for an
    orthographic one. UserError for a skewed camera, which the integrators do not model."""
    if calibration is None or calibration.intrinsics is None:
        return None
    k = np.asarray(calibration.intrinsics, dtype=np.float64)
    if k[0, 1] != 0:
        raise UserError(f"camera intrinsics with skew {k[0, 1]:g}: the integrators model a camera without skew")
    return Camera.from_matrix(k)


def depth_image(depth: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, float, float]:
    """``depth.png``'s uint16 pixels and its ``offset`` and ``scale`` (see the module docstring)."""
    inside = mask & np.isfinite(depth)
    if not inside.any():
        return np.zeros(depth.shape, np.uint16), 0.0, 1.0
    low, high = float(depth[inside].min()), float(depth[inside].max())
    scale = high - low if high > low else 1.0
    image = np.zeros(depth.shape, np.uint16)
    image[inside] = 1 + np.floor((depth[inside] - low) / scale * PNG_LEVELS + 0.5).astype(np.uint16)
    return image, low, scale


def mesh_faces(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(P,) flat pixel index of each vertex (the pixels of ``mask`` in row-major order) and (F, 3)
    int64 triangles into them: per 2×2 block a = (v, u), b = (v, u+1), c = (v+1, u), d = (v+1, u+1),
    the triangles (a, c, b) and (b, c, d), counter-clockwise seen from the camera, each where its three
    pixels are in ``mask``."""
    height, width = mask.shape
    vertex = np.full(mask.shape, -1, np.int64)
    flat = np.flatnonzero(mask)
    vertex.ravel()[flat] = np.arange(flat.size)
    a, b = vertex[:-1, :-1], vertex[:-1, 1:]
    c, d = vertex[1:, :-1], vertex[1:, 1:]
    faces = []
    for triangle in ((a, c, b), (b, c, d)):
        stacked = np.stack([corner.ravel() for corner in triangle], axis=1)
        faces.append(stacked[(stacked >= 0).all(axis=1)])
    return flat, np.concatenate(faces) if height > 1 and width > 1 else np.zeros((0, 3), np.int64)


def vertex_colours(albedo: np.ndarray | None, flat: np.ndarray) -> np.ndarray | None:
    """(P, 4) uint8 RGBA of the vertices from the albedo, scaled so its 99th percentile is white
    (albedo is relative to the light's intensity, so only its proportions are meaningful); None
    without an albedo."""
    if albedo is None or albedo.ndim != 3 or albedo.shape[2] != 3:
        return None
    rgb = np.asarray(albedo, dtype=np.float64).reshape(-1, 3)[flat]
    finite = rgb[np.isfinite(rgb).all(axis=1)]
    top = float(np.percentile(finite, 99.0)) if finite.size else 1.0
    scaled = np.clip(np.nan_to_num(rgb / (top if top > 0 else 1.0)) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return np.concatenate([scaled, np.full((flat.size, 1), 255, np.uint8)], axis=1)


def build_mesh(surface: Surface, albedo: np.ndarray | None, camera: Camera | None) -> Any:
    """The trimesh ``Trimesh`` of ``surface`` (see the module docstring), unprocessed so its vertices
    stay one per pixel in row-major order."""
    import trimesh

    flat, faces = mesh_faces(surface.mask)
    vertices = points(surface, camera).reshape(-1, 3)[flat]
    return trimesh.Trimesh(vertices=vertices, faces=faces, vertex_colors=vertex_colours(albedo, flat), process=False)


def write_mesh(folder: Path, mesh: Any) -> None:
    """``mesh.ply`` (binary, with vertex colours) and ``mesh.obj`` into ``folder``, atomically."""
    import trimesh

    with psfmt.atomic_path(folder / MESH_PLY) as tmp:
        tmp.write_bytes(mesh.export(file_type="ply"))
    text = trimesh.exchange.obj.export_obj(mesh, include_normals=False, include_color=True, include_texture=False)
    with psfmt.atomic_path(folder / MESH_OBJ) as tmp:
        tmp.write_text(text, encoding="utf-8")


def integrate_inputs(
    inputs: SurfaceInputs, integrator: Entry, options: dict[str, Any], folder: Path,
) -> dict[str, Any]:
    """Integrate ``inputs.normal`` with the registered ``integrator`` and write the depth and mesh
    files into ``folder``; returns the ``surface`` entry of ``result.json`` (see the module docstring).
    Raises UserError when no pixel has a normal."""
    if not inputs.mask.any():
        raise UserError(f"{folder}: the normal map has no pixel to integrate")
    surface: Surface = integrator.obj().integrate(inputs.normal, inputs.mask, options, camera=inputs.camera)
    depth = np.where(surface.mask, surface.depth, np.nan)
    write_npy(folder / DEPTH_NPY, depth.astype(np.float32))
    image, offset, scale = depth_image(depth, surface.mask)
    write_png(folder / DEPTH_PNG, image)
    mesh = build_mesh(surface, inputs.albedo, inputs.camera)
    write_mesh(folder, mesh)
    entry: dict[str, Any] = {
        "integrator": integrator.name,
        "plugin": integrator.plugin,
        "options": options,
        "projection": surface.projection,
        "seconds": surface.seconds,
        "depth": {"npy": DEPTH_NPY, "png": DEPTH_PNG, "offset": offset, "scale": scale, "levels": PNG_LEVELS},
        "mesh": {"ply": MESH_PLY, "obj": MESH_OBJ, "vertices": int(len(mesh.vertices)), "faces": int(len(mesh.faces))},
        "depth_error": None,
    }
    if inputs.truth_depth is not None:
        # a perspective surface is known up to scale, an orthographic one in pixels against truth in
        # the capture's units: both need the scale as well as the offset aligned
        error = depth_error(depth, inputs.truth_depth, surface.mask & inputs.mask)
        truth = inputs.truth_depth[surface.mask & inputs.mask]
        extent = float(np.nanmax(truth) - np.nanmin(truth)) if truth.size else 0.0
        entry["depth_error"] = {
            "rmse": error.rmse,
            "rmse_of_range": error.rmse / extent if extent > 0 else None,
            "scale": error.scale,
            "offset": error.offset,
            "pixels": error.pixels,
            "alignment": "least-squares scale and offset over the mask",
        }
    return entry


def read_summary(folder: Path) -> dict[str, Any]:
    """``folder``'s ``result.json`` as a dict; UserError naming the file when it is missing, too
    large, or not a JSON object (``scoring.read_result_json``)."""
    path = folder / RESULT_FILE
    if not path.is_file():
        raise UserError(f"{path}: no result.json (not a result folder)")
    return read_result_json(path)


def folder_inputs(folder: Path, capture: Path | None) -> SurfaceInputs:
    """The normal map (``normal.npy``), its mask (its solved pixels, ``solved_pixels``) and albedo (``albedo.npy`` when
    the solver wrote one) of a result ``folder``; the ground-truth depth and camera of ``capture``
    when given (a result's own ``capture`` entry is not followed: a folder is read, not where it points)."""
    normal = read_normal_npy(folder / "normal.npy")
    mask = solved_pixels(normal)
    albedo = None
    if (folder / "albedo.npy").is_file():
        candidate = read_npy(folder / "albedo.npy")
        albedo = candidate if candidate.shape == (*mask.shape, 3) else None
    truth, camera = capture_truth(capture, mask.shape) if capture is not None else (None, None)
    return SurfaceInputs(normal, mask, albedo, truth, camera)


def add_surface(folder: Path, summary: dict[str, Any], inputs: SurfaceInputs, integrator: Entry,
                options: dict[str, Any]) -> dict[str, Any]:
    """Integrate into ``folder`` and rewrite its ``result.json`` with the ``surface`` entry, last and
    atomically; returns the new summary."""
    summary = {**summary, "surface": integrate_inputs(inputs, integrator, options, folder)}
    with psfmt.atomic_path(folder / RESULT_FILE) as tmp:
        tmp.write_text(summary_json(summary) + "\n")
    return summary


def surface_line(entry: dict[str, Any]) -> str:
    """One line for the terminal about a ``surface`` entry: integrator, seconds, mesh size and depth error."""
    error = entry.get("depth_error")
    depth = "no ground-truth depth" if error is None else (
        f"depth RMSE {error['rmse']:.4g} after scale/offset alignment"
        + ("" if error.get("rmse_of_range") is None else f" ({100 * error['rmse_of_range']:.2f} % of the depth range)")
    )
    mesh = entry["mesh"]
    return (f"surface by {entry['integrator']} ({entry['projection']}): {entry['seconds']:.2f} s, "
            f"{mesh['vertices']} vertices, {mesh['faces']} faces, {depth}")
