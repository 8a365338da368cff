"""Mitsuba BSDFs from a scene's material maps.

- ``roughplastic``: the scene's albedo map as diffuse reflectance under a GGX dielectric coating of
  α = r² (r the median roughness of the mask: Mitsuba's plastic takes one value) and the index of
  refraction of the median F0, η = (1 + √F0)/(1 − √F0) (F0 0.04 → 1.5).
- ``roughconductor``: a metal (``conductor``, Mitsuba's measured spectra: Cu copper by default)
  with GGX α = r², its reflectance modulated by the albedo map's brightness scaled to a maximum of 1
  (a tarnish pattern), so a textured scene stays textured.
- ``principled``: Disney's principled BSDF with the albedo map as base colour, the median roughness
  and metallic, and specular = F0/0.08 (its convention: 0.5 ↔ F0 0.04).

Ground truth keeps the scene's maps (albedo, F0, roughness, metallic): for the conductor they do not
describe the metal.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from pstoolkit.sim.scenes import SceneMaps

BSDFS = ("roughplastic", "roughconductor", "principled")
CONDUCTORS = ("Cu", "Au", "Ag", "Al", "Cr", "Fe", "Ni", "Ti")


def _median(values: np.ndarray, mask: np.ndarray, default: float) -> float:
    return float(np.median(values[mask])) if mask.any() else default


def _texture(mi: Any, image: np.ndarray) -> dict[str, Any]:
    """A bitmap texture of (H, W, C) float values in [0, 1], looked up raw (linear), bilinear,
    clamped at the border; texture coordinate v runs down the image as the mesh's do."""
    return {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(image, dtype=np.float32)), "raw": True,
            "filter_type": "bilinear", "wrap_mode": "clamp"}


def bsdf_dict(mi: Any, maps: SceneMaps, bsdf: str, conductor: str) -> dict[str, Any]:
    """The Mitsuba dict of ``bsdf`` (``BSDFS``) with ``maps``' materials (module docstring)."""
    mask = maps.mask
    r = max(_median(maps.roughness, mask, 0.4), 0.02)
    f0 = float(np.clip(_median(maps.f0.mean(axis=-1), mask, 0.04), 1e-4, 0.9))
    albedo = np.clip(maps.albedo, 0.0, 1.0)
    if bsdf == "roughplastic":
        eta = (1.0 + np.sqrt(f0)) / (1.0 - np.sqrt(f0))
        return {"type": "roughplastic", "distribution": "ggx", "alpha": r * r, "int_ior": float(eta), "ext_ior": 1.0,
                "diffuse_reflectance": _texture(mi, albedo)}
    if bsdf == "roughconductor":
        brightness = albedo.mean(axis=-1, keepdims=True)
        top = float(brightness[mask].max()) if mask.any() else 1.0
        return {"type": "roughconductor", "distribution": "ggx", "alpha": r * r, "material": conductor,
                "specular_reflectance": _texture(mi, brightness / max(top, 1e-6))}
    return {"type": "principled", "base_color": _texture(mi, albedo), "roughness": r,
            "metallic": _median(maps.metallic, mask, 0.0), "specular": float(np.clip(f0 / 0.08, 0.0, 1.0))}
