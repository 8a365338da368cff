"""The frame camera's projection (spec/hybrid-capture.md §9.1): orthographic, or a pinhole (format 1.2).

Conventions (spec §3): the camera frame is right-handed, x right, y up, z towards the camera, lengths
in mm; a pixel ``(u, v)`` is column ``u`` (right) and row ``v`` (down), pixel centres at integers.

A ``perspective`` camera has its centre of projection at the origin of the camera frame and looks
along −z, so the scene lies at z < 0 and a point's depth along the optical axis is ``d = −z > 0``
(the ground-truth ``depth`` map holds z, that is ``−d``). Its intrinsics, float64 (3, 3),

    K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]]     fx, fy, s, cx, cy in frame pixels,

take the point ``X = (x, y, z)`` to the pixel (K applied to ``(x, −y, −z)``, the same point in the
image-style frame x right, y down, z forward)

    u = cx + (fx·x − s·y) / d,    v = cy − fy·y / d,    d = −z,

and the pixel ``(u, v)`` back-projects to the ray ``X = d·r``, ``d > 0``, with

    r = ((u − cx − s·(v − cy)/fy) / fx,  −(v − cy)/fy,  −1)     (s = 0: ((u − cx)/fx, −(v − cy)/fy, −1)).

The direction from a surface point X towards the camera is ``−X/|X|``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

ORTHOGRAPHIC = "orthographic"
PERSPECTIVE = "perspective"
CAMERA_MODELS = (ORTHOGRAPHIC, PERSPECTIVE)
"""Values of ``Calibration.camera_model`` (spec §9.1); ``perspective`` needs format ``PERSPECTIVE_SINCE``."""
PERSPECTIVE_SINCE = (1, 2)
INTRINSICS_SHAPE = (3, 3)


def intrinsics_problem(k: np.ndarray) -> str | None:
    """Why the float (3, 3) array ``k`` is not a pinhole matrix ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]``
    with finite entries and fx, fy > 0 (pixels); None when it is one."""
    if k.shape != INTRINSICS_SHAPE:
        return f"has shape {k.shape}, expected {INTRINSICS_SHAPE}"
    if not np.all(np.isfinite(k)):
        return "holds NaN or infinite values"
    fx, fy = float(k[0, 0]), float(k[1, 1])
    if not (fx > 0 and fy > 0):
        return f"fx and fy must be positive, got fx = {fx:g}, fy = {fy:g}"
    if k[1, 0] != 0:
        return f"element [1, 0] is {float(k[1, 0]):g}, expected 0 (K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]])"
    if tuple(float(x) for x in k[2]) != (0.0, 0.0, 1.0):
        return f"last row is ({', '.join(f'{float(x):g}' for x in k[2])}), expected (0, 0, 1)"
    return None


def camera_problem(model: Any, intrinsics: np.ndarray | None) -> str | None:
    """Why a camera model and its intrinsics (None, or float (3, 3)) do not go together (spec §9.1):
    ``perspective`` needs valid intrinsics, ``orthographic`` has none; None when they do."""
    if not (isinstance(model, str) and model in CAMERA_MODELS):
        return f"camera_model {model!r} is not one of {', '.join(CAMERA_MODELS)}"
    if model == ORTHOGRAPHIC:
        return None if intrinsics is None else "intrinsics are given, but camera_model is 'orthographic'"
    if intrinsics is None:
        return "camera_model 'perspective' needs intrinsics, the (3, 3) matrix K"
    problem = intrinsics_problem(np.asarray(intrinsics, dtype=np.float64))
    return None if problem is None else f"intrinsics {problem}"


def pixel_rays(intrinsics: np.ndarray, u: Any, v: Any) -> np.ndarray:
    """Rays (..., 3) float64 in the camera frame through the pixels ``(u, v)`` (arrays of one shape,
    frame pixels), scaled to z = −1: the surface point of a pixel whose depth along the optical axis
    is ``d`` mm (z = −d) is ``d · ray``."""
    k = np.asarray(intrinsics, dtype=np.float64)
    fx, s, cx, fy, cy = k[0, 0], k[0, 1], k[0, 2], k[1, 1], k[1, 2]
    u, v = np.broadcast_arrays(np.asarray(u, dtype=np.float64), np.asarray(v, dtype=np.float64))
    du, dv = u - cx, v - cy
    return np.stack([(du - s * dv / fy) / fx, -dv / fy, np.full(du.shape, -1.0)], axis=-1)


def project(intrinsics: np.ndarray, points: Any) -> np.ndarray:
    """Frame pixels (..., 2) float64 ``(u, v)`` of camera-frame points (..., 3) in mm with z < 0."""
    k = np.asarray(intrinsics, dtype=np.float64)
    p = np.asarray(points, dtype=np.float64)
    d = -p[..., 2]
    u = k[0, 2] + (k[0, 0] * p[..., 0] - k[0, 1] * p[..., 1]) / d
    v = k[1, 2] - k[1, 1] * p[..., 1] / d
    return np.stack([u, v], axis=-1)
