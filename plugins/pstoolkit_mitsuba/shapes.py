"""What the renderer and the ``mesh`` scene build in Mitsuba alike: a triangle mesh from arrays, and
the orthographic camera that sees frame pixel (u, v) centred on x = u + ½ − W/2, y = H/2 − v − ½
(frame pixels, camera frame: x right, y up, z towards the camera), looking down −z."""

from __future__ import annotations

from typing import Any

import numpy as np

from pstoolkit import UserError

CAMERA_HEIGHT_PX = 1e5
"""Height of the orthographic camera above z = 0, frame pixels: above any surface of a frame."""


def planar_texcoords(positions: np.ndarray, height: int, width: int) -> np.ndarray:
    """(N, 2) float32 texture coordinates of points projected on the image (u right, v down, [0, 1]
    over the frame, clamped), so an albedo map lies on a surface as the camera sees it."""
    u = (positions[:, 0] + width / 2.0) / width
    v = (height / 2.0 - positions[:, 1]) / height
    return np.clip(np.stack([u, v], axis=-1), 0.0, 1.0).astype(np.float32)


def triangle_mesh(mi: Any, positions: np.ndarray, faces: np.ndarray, texcoords: np.ndarray,
                  normals: np.ndarray | None = None, bsdf: Any = None) -> Any:
    """A Mitsuba mesh of ``positions`` (N, 3), ``faces`` (F, 3), ``texcoords`` (N, 2) and vertex
    ``normals`` (N, 3), or, without them, the area-weighted normals Mitsuba computes."""
    if not len(faces):
        raise UserError("the surface has no triangles: nothing to render")
    props = mi.Properties()
    if bsdf is not None:
        props["bsdf"] = bsdf
    shape = mi.Mesh("surface", len(positions), len(faces), props, has_vertex_normals=True, has_vertex_texcoords=True)
    params = mi.traverse(shape)
    arrays = {"vertex_positions": positions, "vertex_texcoords": texcoords, "faces": faces}
    if normals is not None:
        arrays["vertex_normals"] = normals
    # the parameter types are the variant's arrays (scalar: ArrayXf/ArrayXu, llvm: Float/UInt32)
    for key, array in arrays.items():
        params[key] = type(params[key])(np.ascontiguousarray(array).ravel())
    params.update()
    if normals is None:
        shape.recompute_vertex_normals()
    return shape


def orthographic_sensor(mi: Any, height: int, width: int, spp: int, pixel_format: str = "rgb") -> dict[str, Any]:
    """The camera of the module docstring with a box filter (a pixel is the mean over its footprint)."""
    return {
        "type": "orthographic",
        "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, CAMERA_HEIGHT_PX], target=[0, 0, 0], up=[0, 1, 0])
        @ mi.ScalarTransform4f().scale([width / 2.0, height / 2.0, 1.0]),
        "near_clip": 1.0,
        "far_clip": 4.0 * CAMERA_HEIGHT_PX,
        "film": {"type": "hdrfilm", "width": width, "height": height, "rfilter": {"type": "box"}, "pixel_format": pixel_format},
        "sampler": {"type": "independent", "sample_count": spp},
    }
