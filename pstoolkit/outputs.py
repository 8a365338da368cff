"""The files ``pstoolkit run`` writes beside the normal map: a solver's further maps and the error map.

Image maps — grey (H, W) or RGB (H, W, 3) at the normal map's size — become 16-bit PNGs with
pixel = round(value / scale · 65535), clipped to [0, 65535], and 0 outside the mask, so
value = pixel / 65535 · scale. The scale is 1 for a grey map whose values all lie in [0, 1]
(roughness, metallic: the PNG reads absolutely), else the 99th percentile of the map's finite values
inside the mask — a robust maximum, so a few specular outliers do not darken the whole image. Every
map is also written as ``<name>.npy`` (float maps as float32); a map that is not an image, such as a
per-frame ``normal_sequence`` (N, H, W, 3), only as ``.npy``.

``error.png`` shows the angular error from 0 to ``error_max_deg`` degrees through OpenCV's Turbo
colormap (dark blue at 0°, through cyan, green and yellow, to dark red at ``error_max_deg`` and above),
8-bit RGB, black outside the ground-truth mask.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from pstoolkit.normalmap import write_npy, write_png
from pstoolkit.registry import PluginError

ROBUST_PERCENTILE = 99.0
PNG_TOP = 65535
RESERVED_MAPS = frozenset({"normal", "mask", "error"})
"""Names ``run`` uses itself (``normal.png``, the stored mask, ``error.png``), not open to solver maps."""
_MAP_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_-]*")


@dataclass
class MapOutput:
    """One solver map ready to write: ``array`` for ``<name>.npy``; ``image`` (uint16 grey or RGB)
    for ``<name>.png`` with its ``scale`` (value = pixel / 65535 · scale), both None when the map is
    not an image."""

    name: str
    array: np.ndarray
    image: np.ndarray | None = None
    scale: float | None = None

    def files(self) -> dict[str, object]:
        """The entry for result.json: the file names and the PNG scale."""
        entry: dict[str, object] = {"npy": f"{self.name}.npy", "shape": list(self.array.shape)}
        if self.image is not None:
            entry["png"] = f"{self.name}.png"
            entry["scale"] = self.scale
        return entry


def map_scale(values: np.ndarray, mask: np.ndarray) -> float:
    """1 for a grey map within [0, 1]; else the robust maximum of the finite values inside ``mask``
    (1 when there are none or it is not positive)."""
    inside = values[mask]
    inside = inside[np.isfinite(inside)]
    if inside.size == 0:
        return 1.0
    if values.ndim == 2 and inside.min() >= 0.0 and inside.max() <= 1.0:
        return 1.0
    top = float(np.percentile(inside, ROBUST_PERCENTILE))
    return top if top > 0.0 else 1.0


def encode_map(values: np.ndarray, mask: np.ndarray, scale: float) -> np.ndarray:
    """uint16 pixels round(value / scale · 65535), clipped; 0 outside ``mask`` and where not finite."""
    scaled = np.nan_to_num(values / scale * PNG_TOP, nan=0.0, posinf=PNG_TOP, neginf=0.0)
    image = np.clip(np.floor(scaled + 0.5), 0, PNG_TOP).astype(np.uint16)
    image[~mask] = 0
    return image


def prepare_maps(maps: dict[str, np.ndarray], mask: np.ndarray, blame: str) -> list[MapOutput]:
    """Check and encode a solver's ``maps`` against its (H, W) ``mask``; ``blame`` names the plugin and
    solver in the PluginError a malformed map raises."""
    outputs = []
    for name, value in maps.items():
        if not isinstance(name, str) or not _MAP_NAME.fullmatch(name) or name in RESERVED_MAPS:
            raise PluginError(
                f"{blame} returned a map named {name!r}: names are letters, digits, '_' and '-', "
                f"not {', '.join(sorted(RESERVED_MAPS))}"
            )
        array = np.asarray(value)
        if array.dtype.kind not in "biuf":
            raise PluginError(f"{blame} returned map {name!r} of dtype {array.dtype}, expected numbers")
        if array.dtype.kind == "f":
            array = array.astype(np.float32)
        image_like = array.shape[:2] == mask.shape and (array.ndim == 2 or (array.ndim == 3 and array.shape[2] in (1, 3)))
        if not image_like:
            outputs.append(MapOutput(name, array))
            continue
        values = array[..., 0] if array.ndim == 3 and array.shape[2] == 1 else array
        values = values.astype(np.float64)
        scale = map_scale(values, mask)
        outputs.append(MapOutput(name, array, encode_map(values, mask, scale), scale))
    return outputs


def error_to_rgb(error_deg: np.ndarray, error_max_deg: float) -> np.ndarray:
    """8-bit RGB (H, W, 3) of an angular-error map through the Turbo colormap over 0…``error_max_deg``
    degrees (larger errors saturate); NaN pixels (outside the mask) are black."""
    inside = np.isfinite(error_deg)
    level = np.clip(np.where(inside, error_deg, 0.0) / error_max_deg * 255.0 + 0.5, 0, 255).astype(np.uint8)
    rgb = cv2.applyColorMap(level, cv2.COLORMAP_TURBO)[..., ::-1].copy()
    rgb[~inside] = 0
    return rgb


def write_maps(folder: Path, outputs: list[MapOutput]) -> None:
    """Write each prepared map as ``<name>.npy`` and, for images, ``<name>.png`` into ``folder``."""
    for output in outputs:
        write_npy(folder / f"{output.name}.npy", output.array)
        if output.image is not None:
            write_png(folder / f"{output.name}.png", output.image)


def write_error_map(folder: Path, error_deg: np.ndarray, error_max_deg: float) -> None:
    """``error.npy`` (float32 degrees, NaN outside the mask) and ``error.png`` (Turbo, see the module)."""
    write_npy(folder / "error.npy", error_deg.astype(np.float32))
    write_png(folder / "error.png", error_to_rgb(error_deg, error_max_deg))
