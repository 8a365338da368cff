"""How the viewer turns linear values into screen pixels, and the page's relighting in Python.

The page (``static/shading.js``) shades every pixel inside the mask with the toolkit's BRDF — GGX as
``pstoolkit.optics.brdf.GGX`` (Lambertian albedo plus a GGX lobe with F0 and roughness), or
Lambertian when the result has no F0 or roughness map, albedo 1 when it has no albedo — under a unit
light direction l (camera frame: x right, y up, z to the camera) seen from v = (0, 0, 1), times the
light's RGB intensity and the exposure, and shows it as ``to_display``. ``relight`` computes the same
picture here through the toolkit's own torch BRDFs, so a test can hold the page to them.
"""

from __future__ import annotations

import numpy as np

GAMMA = 1.0 / 2.2
"""Display encoding: 255 · clip(value, 0, 1)^GAMMA, rounded half up (linear values look too dark)."""
BACKGROUND = (24, 24, 27)
"""The page's RGB outside the mask."""


def to_display(linear: np.ndarray) -> np.ndarray:
    """uint8 pixels of linear values (any shape; 1 = white): round(255 · clip(v, 0, 1)^GAMMA), with
    NaN as 0 — exactly what the page computes."""
    values = np.nan_to_num(np.asarray(linear, dtype=np.float64), nan=0.0, posinf=1.0, neginf=0.0)
    return np.floor(255.0 * np.clip(values, 0.0, 1.0) ** GAMMA + 0.5).astype(np.uint8)


def unit_light(light: tuple[float, float, float] | np.ndarray) -> np.ndarray:
    """``light`` (3,) scaled to unit length (float64); a ValueError for a zero or non-finite vector."""
    vector = np.asarray(light, dtype=np.float64).reshape(3)
    norm = float(np.linalg.norm(vector))
    if not np.isfinite(norm) or norm == 0.0:
        raise ValueError(f"light direction {vector.tolist()} is not a direction")
    return vector / norm


def relight(
    maps: dict[str, np.ndarray],
    mask: np.ndarray,
    light: tuple[float, float, float] | np.ndarray,
    exposure: float,
    intensity: tuple[float, float, float] = (1.0, 1.0, 1.0),
) -> np.ndarray:
    """The page's relit picture: uint8 RGB (H, W, 3), ``BACKGROUND`` outside ``mask`` (H, W) bool.

    ``maps``: ``normal`` (H, W, 3) and optionally ``albedo``, ``f0`` ((H, W, 3) or (H, W)) and
    ``roughness`` (H, W); GGX with both F0 and roughness, else Lambertian, in float64 through
    ``pstoolkit.optics.brdf``. ``light`` is normalised; ``exposure`` and ``intensity`` (RGB) scale
    the radiance before ``to_display``."""
    import torch

    from pstoolkit.optics.brdf import GGX, Lambertian

    def tensor(name: str, default: float) -> torch.Tensor:
        value = maps.get(name)
        if value is None:
            return torch.tensor(default, dtype=torch.float64)
        array = np.asarray(value, dtype=np.float64)
        return torch.from_numpy(array if array.ndim == 3 else array[..., None])

    n = torch.from_numpy(np.asarray(maps["normal"], dtype=np.float64))
    l = torch.from_numpy(unit_light(light)).expand_as(n)
    v = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand_as(n)
    albedo = tensor("albedo", 1.0)
    if "f0" in maps and "roughness" in maps:
        radiance = GGX().shade(n, l, v, albedo=albedo, f0=tensor("f0", 0.0), roughness=tensor("roughness", 0.5))
    else:
        radiance = Lambertian().shade(n, l, v, albedo=albedo)
    linear = radiance.numpy() * np.asarray(intensity, dtype=np.float64) * exposure
    image = to_display(linear)
    image[~np.asarray(mask, dtype=bool)] = BACKGROUND
    return image
