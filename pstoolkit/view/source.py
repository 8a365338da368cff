"""What the viewer shows: the maps of a result folder, or of a capture's stored result or ground truth.

``load_result_folder`` reads ``normal.npy`` and whichever of ``albedo``, ``f0``, ``roughness``,
``error`` and ``depth`` (``<name>.npy``) exist, plus ``result.json``; ``load_capture_maps`` takes the
same maps from a capture's stored result (``/results/<name>``) or, without one, its ground truth.
Either gives a ``ViewData``: float32 maps at the normal map's (H, W), the pixels to draw, the strings
to show (all from files, so untrusted: the page sets them as text, never as markup) and the capture,
if any, whose frames and events the page scrubs.

Sizes are checked before anything is allocated: a ``.npy`` file's header is parsed and checked
against the file's length without reading the data, and its shape against ``MAX_PIXELS`` and the
normal map's size, before it is memory-mapped and copied. Only regular files inside the folder are
read (``in_folder``): a map or result.json that is a link leading out of it is refused. Errors are
``UserError``s naming the file; a further map that does not fit is left out with a note instead.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from psfmt.text import printable
from pstoolkit._shared.vectors import solved_pixels
from pstoolkit.errors import UserError
from pstoolkit.evaluation.scoring import read_result_json
from pstoolkit.io.normalmap import npy_header

MAP_NAMES = ("normal", "albedo", "f0", "roughness", "error", "depth")
"""The maps the viewer shows, in this order, whichever exist (``normal`` always does)."""
MAX_PIXELS = 1 << 24
"""Most pixels (4096²) of a map; a browser would not draw more at interactive rates anyway."""
DISPLAY_WHITE = 0.8
"""The brightest diffuse pixel (the 99th percentile of the albedo) under a light of intensity 1 along
the normal is shown at this share of white by default, as the simulator's diffuse auto gain does."""
DEFAULT_ERROR_MAX_DEG = 30.0
_TEXT_KEYS = ("name", "solver", "plugin", "object", "capture", "capture_kind", "device", "pstoolkit_version")
_NUMBER_KEYS = ("mae_deg", "mae_solved_deg", "median_deg", "coverage", "seconds", "data_rate")


@dataclass
class ViewData:
    """The maps and strings the page gets.

    ``maps``: name → float32 (H, W) or (H, W, C) with C in (1, 3), every one at the normal map's
    (H, W); ``normal`` is (H, W, 3), zero outside ``mask`` (H, W) bool, and every map is NaN or
    finite. ``folder`` is the result folder the page may fetch files from (None for a capture).
    ``label`` names what is shown; ``info`` holds result.json's strings and numbers (or the stored
    result's), ``options`` the solver's options, ``notes`` what was left out and why — all
    untrusted text. ``capture`` is the capture to scrub (None: none known or found).
    """

    maps: dict[str, np.ndarray]
    mask: np.ndarray
    label: str
    folder: Path | None = None
    info: dict[str, Any] = field(default_factory=dict)
    options: dict[str, Any] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    capture: Path | None = None
    error_max_deg: float = DEFAULT_ERROR_MAX_DEG

    @property
    def height(self) -> int:
        return int(self.mask.shape[0])

    @property
    def width(self) -> int:
        return int(self.mask.shape[1])

    @property
    def brdf(self) -> str:
        """``ggx`` when both F0 and roughness maps exist, else ``lambertian`` (the page's shading)."""
        return "ggx" if "f0" in self.maps and "roughness" in self.maps else "lambertian"

    def exposure(self) -> float:
        """The default display gain: ``DISPLAY_WHITE`` over the 99th percentile of the albedo's
        largest channel inside the mask (albedo 1 when there is no albedo map)."""
        albedo = self.maps.get("albedo")
        if albedo is None or not self.mask.any():
            return DISPLAY_WHITE
        top = albedo.max(axis=-1) if albedo.ndim == 3 else albedo
        inside = top[self.mask]
        inside = inside[np.isfinite(inside)]
        level = float(np.percentile(inside, 99.0)) if inside.size else 0.0
        return DISPLAY_WHITE / level if level > 0.0 else DISPLAY_WHITE

    def value_range(self, name: str) -> tuple[float, float]:
        """The range the page maps to black…white (or the colour map) for map ``name``: [−1, 1] for
        normals, [0, error_max_deg] for errors, the finite min…max inside the mask for depth, else
        0 to the 99th percentile (1 for a map within [0, 1])."""
        if name == "normal":
            return -1.0, 1.0
        if name == "error":
            return 0.0, self.error_max_deg
        values = self.maps[name][self.mask]
        values = values[np.isfinite(values)]
        if values.size == 0:
            return 0.0, 1.0
        if name == "depth":
            lo, hi = float(values.min()), float(values.max())
            return (lo, hi) if hi > lo else (lo - 1.0, lo + 1.0)
        if values.min() >= 0.0 and values.max() <= 1.0:
            return 0.0, 1.0
        top = float(np.percentile(values, 99.0))
        return 0.0, top if top > 0.0 else 1.0


def read_map(path: Path, shape_hw: tuple[int, int] | None) -> np.ndarray:
    """A numeric .npy map as float32 (H, W) or (H, W, C), C in (1, 3), non-finite values as NaN.

    ``shape_hw``: the (H, W) it must have (None: any, up to ``MAX_PIXELS``). The file is
    header is read and checked (``npy_header``: a shape the file holds) and the shape held against
    the viewer's limits before the file is memory-mapped and copied. Raises UserError naming the file."""
    shape, _ = npy_header(path)
    if len(shape) not in (2, 3) or (len(shape) == 3 and shape[2] not in (1, 3)) or 0 in shape:
        raise UserError(f"{path}: expected an (H, W), (H, W, 1) or (H, W, 3) map, got shape {shape}")
    if shape[0] * shape[1] > MAX_PIXELS:
        raise UserError(f"{path}: {shape[1]}×{shape[0]} map is over the viewer's {MAX_PIXELS} pixels")
    if shape_hw is not None and tuple(shape[:2]) != tuple(shape_hw):
        raise UserError(f"{path}: map is {shape[1]}×{shape[0]}, the normal map {shape_hw[1]}×{shape_hw[0]}")
    try:
        mapped = np.load(path, mmap_mode="r", allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise UserError(f"{path}: not a readable .npy map ({printable(exc)})") from None
    return _finite(np.array(mapped, dtype=np.float32))


def in_folder(folder: Path, name: str) -> Path | None:
    """``folder / name`` when it is a regular file inside ``folder`` once every link is resolved;
    None when it does not exist; UserError when it leads out of the folder or is not a file — the
    viewer reads and serves nothing from outside the folder it was given."""
    path = folder / name
    if not os.path.lexists(path):
        return None
    try:
        target = path.resolve(strict=True)
        inside = target.is_relative_to(folder.resolve(strict=True)) and target.is_file()
    except (OSError, RuntimeError):  # a dangling link, a loop
        inside = False
    if not inside:
        raise UserError(f"{path}: leads out of the result folder or is not a regular file; the viewer reads only files inside it")
    return path


def _finite(array: np.ndarray) -> np.ndarray:
    array[~np.isfinite(array)] = np.nan
    return array


def _normal_and_mask(normal: np.ndarray, mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The normal map zeroed where it is not solved (``solved_pixels``) or outside ``mask``; and the mask of the rest."""
    if normal.ndim != 3 or normal.shape[2] != 3:
        raise UserError(f"normal map has shape {normal.shape}, expected (H, W, 3)")
    keep = solved_pixels(normal)
    if mask is not None:
        keep &= mask
    return np.where(keep[..., None], normal, np.float32(0.0)).astype(np.float32), keep


def _summary_fields(summary: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """(info, options) from result.json: its known strings and finite numbers, and its options with
    plain JSON values; anything of another type is left out, as a crafted file may hold anything."""
    info: dict[str, Any] = {k: summary[k] for k in _TEXT_KEYS if isinstance(summary.get(k), str)}
    for key in _NUMBER_KEYS:
        value = summary.get(key)
        if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
            info[key] = value
    raw = summary.get("options")
    return info, plain_options(raw) if isinstance(raw, dict) else {}


def plain_options(options: dict[Any, Any]) -> dict[str, Any]:
    """The options whose values are strings, booleans, None or finite numbers (the page shows them
    as text; anything nested or non-finite, which JSON cannot carry to the page, is left out)."""

    def plain(value: Any) -> bool:
        if isinstance(value, float):
            return math.isfinite(value)
        return value is None or isinstance(value, (str, int, bool))

    return {str(k): v for k, v in options.items() if plain(v)}


def load_result_folder(folder: Path, capture: Path | None = None) -> ViewData:
    """The maps of a result folder written by ``pstoolkit run`` (``normal.npy`` required).

    ``capture``: the capture it was solved from, given by the user (None: no capture to scrub; the
    path result.json names is only shown in a note, never opened — a folder's files do not lead the
    viewer out of the folder). Raises UserError for a missing folder or normal map, or an unreadable normal map or
    result.json; a further map that cannot be read or has another size is left out with a note."""
    if not folder.is_dir():
        raise UserError(f"{folder}: not a folder")
    normal_path = in_folder(folder, "normal.npy")
    if normal_path is None:
        raise UserError(f"{folder}: no normal.npy (a result folder holds the files `pstoolkit run` writes)")
    summary_path = in_folder(folder, "result.json")
    summary = {} if summary_path is None else read_result_json(summary_path)
    normal, mask = _normal_and_mask(read_map(normal_path, None))
    maps: dict[str, np.ndarray] = {"normal": normal}
    notes: list[str] = []
    for name in MAP_NAMES[1:]:
        try:
            path = in_folder(folder, f"{name}.npy")
            if path is not None:
                maps[name] = read_map(path, mask.shape)
        except UserError as exc:
            notes.append(f"left out {name}: {exc}")
    info, options = _summary_fields(summary)
    error_max = summary.get("error_max_deg")
    label = " · ".join(info[k] for k in ("object", "name") if k in info) or folder.name
    if capture is None and isinstance(summary.get("capture"), str):
        notes.append(f"result.json names the capture {summary['capture']}: pass --capture FILE to scrub its frames and events")
    data = ViewData(maps, mask, label, folder=folder, info=info, options=options, notes=notes, capture=capture)
    if isinstance(error_max, (int, float)) and not isinstance(error_max, bool) and 0 < error_max < 1e6:
        data.error_max_deg = float(error_max)
    return data


def _checked(value: Any, shape_hw: tuple[int, int]) -> np.ndarray | None:
    """A stored map as float32 if it is a numeric image at ``shape_hw`` (None otherwise)."""
    array = np.asarray(value)
    if array.dtype.kind not in "biuf" or array.shape[:2] != shape_hw or array.ndim not in (2, 3):
        return None
    if array.ndim == 3 and array.shape[2] not in (1, 3):
        return None
    return _finite(array.astype(np.float32))


def load_capture_maps(capture: Any, path: Path, result: str | None = None) -> ViewData:
    """The maps of an open capture (``psfmt.Capture``, read from ``path``): the stored result
    ``result`` (None: the first stored one), or the ground truth when it stores none.

    Raises UserError when ``result`` is not stored, or the capture has neither results nor ground
    truth normals. The psfmt reader has already refused maps beyond its limits."""
    gt = capture.ground_truth
    if result is not None and result not in capture.results:
        stored = ", ".join(sorted(capture.results)) or "none"
        raise UserError(f"{path}: no stored result {result!r} (stored: {stored})")
    name = result if result is not None else next(iter(capture.results), None)
    if name is not None:
        stored = capture.results[name]
        source = {key: stored.maps[key] for key in ("normal", "mask", *MAP_NAMES[1:]) if key in stored.maps}
        info: dict[str, Any] = {"name": name, "solver": stored.solver, "seconds": stored.seconds}
        options, label = plain_options(stored.options) if isinstance(stored.options, dict) else {}, f"{path.stem} · {name}"
    elif gt is not None and gt.normal is not None:
        source = {"normal": gt.normal, "mask": gt.mask, "albedo": gt.albedo, "depth": gt.depth, **gt.materials}
        info, options, label = {"name": "ground truth"}, {}, f"{path.stem} · ground truth"
    else:
        raise UserError(f"{path}: the capture stores no result and no ground-truth normals to show")
    if source.get("normal") is None:
        raise UserError(f"{path}: {label}: no normal map")
    normal = _checked(source["normal"], np.shape(source["normal"])[:2])
    if normal is None or normal.ndim != 3 or normal.shape[0] * normal.shape[1] > MAX_PIXELS:
        raise UserError(f"{path}: {label}: the normal map is not a float (H, W, 3) map within {MAX_PIXELS} pixels")
    hw = normal.shape[:2]
    mask = source.get("mask")
    mask = np.asarray(mask, dtype=bool) if mask is not None and np.shape(mask) == hw else None
    normal, mask = _normal_and_mask(normal, mask)
    maps: dict[str, np.ndarray] = {"normal": normal}
    notes = []
    for key in MAP_NAMES[1:]:
        if source.get(key) is None:
            continue
        array = _checked(source[key], hw)
        if array is None:
            notes.append(f"left out {key}: not a numeric map at {hw[1]}×{hw[0]}")
            continue
        if key == "depth":
            array[~mask] = np.nan  # the ground truth stores 0 outside the mask; the page wants NaN
        maps[key] = array
    return ViewData(maps, mask, label, info=info, options=options, notes=notes, capture=path)
