"""A scene's height field as a triangle mesh in the camera frame, in frame pixels: vertex (u, v) of
the image at x = u + ½ − W/2 (right), y = H/2 − v − ½ (up), z = the scene's height towards the
camera, so an orthographic camera looking down −z sees pixel (u, v) centred on that vertex.

The grid is padded by one vertex on each side (edge values), so a pixel at the frame's border is
covered like any other; the two triangles of a grid square are kept where their corners lie inside
the mask. A pixel is covered wholly exactly when its 3×3 neighbourhood lies in the mask
(``covered``): its footprint then lies inside the four squares around its vertex.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import binary_erosion

from pstoolkit.sim.scenes import SceneMaps


@dataclass
class HeightMesh:
    """``positions`` (N, 3) float32, ``normals`` (N, 3) float32 (the scene's normals, unit),
    ``texcoords`` (N, 2) float32 (u right, v down, in [0, 1] over the frame) and ``faces`` (F, 3)
    uint32, counter-clockwise seen from the camera."""

    positions: np.ndarray
    normals: np.ndarray
    texcoords: np.ndarray
    faces: np.ndarray


def height_mesh(maps: SceneMaps) -> HeightMesh:
    """The mesh of ``maps``' depth and normals (module docstring)."""
    h, w = maps.mask.shape
    mask = np.pad(maps.mask, 1, mode="edge")
    depth = np.pad(maps.depth, 1, mode="edge")
    normal = np.pad(maps.normal, ((1, 1), (1, 1), (0, 0)), mode="edge")
    v, u = np.mgrid[-1 : h + 1, -1 : w + 1].astype(np.float64)
    index = np.full(mask.shape, -1, dtype=np.int64)
    index[mask] = np.arange(int(mask.sum()))
    positions = np.stack([u[mask] + 0.5 - w / 2.0, h / 2.0 - v[mask] - 0.5, depth[mask]], axis=-1)
    texcoords = np.stack([np.clip((u[mask] + 0.5) / w, 0, 1), np.clip((v[mask] + 0.5) / h, 0, 1)], axis=-1)
    a, b, c, d = index[:-1, :-1], index[:-1, 1:], index[1:, :-1], index[1:, 1:]
    faces = []
    # (a c d) and (a d b): counter-clockwise with y up, so the geometric normals face the camera
    for corners in ((a, c, d), (a, d, b)):
        keep = np.logical_and.reduce([k >= 0 for k in corners])
        faces.append(np.stack([k[keep] for k in corners], axis=-1))
    unit = normal[mask] / np.maximum(np.linalg.norm(normal[mask], axis=-1, keepdims=True), 1e-12)
    return HeightMesh(
        positions.astype(np.float32), unit.astype(np.float32), texcoords.astype(np.float32),
        np.concatenate(faces).astype(np.uint32),
    )


def covered(mask: np.ndarray) -> np.ndarray:
    """(H, W) bool: the pixels of ``mask`` that the height mesh covers wholly (module docstring)."""
    padded = np.pad(mask, 1, mode="edge")
    return binary_erosion(padded, np.ones((3, 3), bool), border_value=0)[1:-1, 1:-1] & mask
