"""A synthetic result folder — a sphere with known maps — for the viewer's tests and benchmark, and to
try the viewer without running a solver: ``python -m pstoolkit.view.sample DIR [SIZE]``.

It has the layout ``pstoolkit run`` writes (``pstoolkit.solve.results``): ``normal.npy``/``.png``,
``albedo``, ``f0`` and ``roughness`` as ``<name>.npy``/``.png`` with their scales in ``result.json``,
``error.npy``/``.png``, and ``depth.npy`` (height towards the camera in pixels, NaN outside the
mask) with ``depth.png``.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from pstoolkit.io.normalmap import error_to_rgb, write_normal_npy, write_normal_png, write_npy, write_png
from pstoolkit.solve.results import encode_map, map_scale, prepare_maps, write_maps

RADIUS = 0.45
"""Sphere radius as a share of the image side."""


def sphere_maps(size: int, *, material: str = "ggx") -> dict[str, np.ndarray]:
    """Maps of a sphere filling ``RADIUS`` of a ``size``² image: ``mask`` (H, W) bool, ``normal``
    (H, W, 3) float32 unit inside and 0 outside, ``albedo`` (H, W, 3) a smooth colour ramp in
    [0.2, 0.9], ``depth`` (H, W) float32 height in pixels (NaN outside), ``error`` (H, W) degrees
    (NaN outside) and, for ``material="ggx"``, ``f0`` (H, W, 3) and ``roughness`` (H, W) varying
    across the sphere (``"lambertian"``: neither)."""
    v, u = np.mgrid[0:size, 0:size].astype(np.float64)
    radius = RADIUS * size
    x = (u - (size - 1) / 2) / radius
    y = -(v - (size - 1) / 2) / radius
    mask = x * x + y * y < 0.98
    z = np.sqrt(np.clip(1.0 - x * x - y * y, 0.0, 1.0))
    normal = np.where(mask[..., None], np.stack([x, y, z], axis=-1), 0.0)
    normal /= np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-12)
    s, t = (x + 1.0) / 2.0, (y + 1.0) / 2.0
    albedo = np.stack([0.2 + 0.7 * s, 0.2 + 0.5 * t, 0.9 - 0.6 * s * t], axis=-1)
    maps = {
        "mask": mask,
        "normal": normal.astype(np.float32),
        "albedo": np.where(mask[..., None], albedo, 0.0).astype(np.float32),
        "depth": np.where(mask, z * radius, np.nan).astype(np.float32),
        "error": np.where(mask, 25.0 * (x * x + y * y), np.nan).astype(np.float32),
    }
    if material == "ggx":
        maps["f0"] = np.where(mask[..., None], np.stack([0.04 + 0.3 * t, 0.04 + 0.2 * t, 0.04 + 0.1 * s], axis=-1), 0.0).astype(np.float32)
        maps["roughness"] = np.where(mask, 0.15 + 0.5 * s, 0.0).astype(np.float32)
    return maps


def write_sphere_result(folder: Path, size: int = 64, *, material: str = "ggx", depth: bool = True,
                        capture: Path | None = None) -> dict[str, np.ndarray]:
    """Write the sphere of ``sphere_maps`` as a result folder (created if needed) and return its maps.
    ``depth=False`` leaves out ``depth.npy``/``.png``; ``capture`` is recorded in ``result.json``."""
    maps = sphere_maps(size, material=material)
    mask = maps["mask"]
    folder.mkdir(parents=True, exist_ok=True)
    write_normal_npy(folder / "normal.npy", maps["normal"])
    write_normal_png(folder / "normal.png", maps["normal"], mask)
    further = prepare_maps({k: maps[k] for k in ("albedo", "f0", "roughness") if k in maps}, mask, "sample")
    write_maps(folder, further)
    write_npy(folder / "error.npy", maps["error"])
    write_png(folder / "error.png", error_to_rgb(maps["error"], 30.0))
    if depth:
        write_npy(folder / "depth.npy", maps["depth"])
        write_png(folder / "depth.png", encode_map(maps["depth"], mask, map_scale(maps["depth"], mask)))
    else:
        del maps["depth"]
    summary = {
        "name": "sample", "solver": "sample", "plugin": "pstoolkit", "object": "sphere",
        "capture": None if capture is None else str(capture), "size": [size, size],
        "maps": {m.name: m.files() for m in further}, "error_max_deg": 30.0, "options": {"material": material},
    }
    (folder / "result.json").write_text(json.dumps(summary, indent=2) + "\n")
    return maps


if __name__ == "__main__":
    write_sphere_result(Path(sys.argv[1]), int(sys.argv[2]) if len(sys.argv) > 2 else 256)
