"""Checks of the per-pixel maps: ``/ground_truth`` (with its materials) and every stored result."""

from __future__ import annotations

import json

import h5py
import numpy as np

from psfmt import layout
from psfmt._validate.findings import Findings
from psfmt._validate.frames import frame_shape
from psfmt._validate.values import check_pixels, dataset, is_number
from psfmt.attributes import attrs
from psfmt.limits import Limits

NORMAL_UNIT_TOLERANCE = 1e-2


def check_map(where: str, ds: h5py.Dataset | None, hw: tuple[int, int] | None, channels: tuple[int, ...], limits: Limits, out: Findings) -> None:
    """A map (absent: nothing to check) is (H, W) or (H, W, C) with C in ``channels`` (1 allows 2-D),
    the frames' ``hw`` when there are frames, and within the pixel limit."""
    if ds is None:
        return
    shapes_ok = (ds.ndim == 2 and 1 in channels) or (ds.ndim == 3 and ds.shape[2] in channels)
    if not shapes_ok:
        out.error(where, f"has shape {ds.shape}, expected (H, W{', C' if channels != (1,) else ''})")
    elif hw is not None and tuple(ds.shape[:2]) != hw:
        out.error(where, f"is {ds.shape[0]}×{ds.shape[1]}, but the frames are {hw[0]}×{hw[1]}")
    else:
        check_pixels(where, ds.shape[0], ds.shape[1], limits, out)


def check_ground_truth(f: h5py.File, limits: Limits, out: Findings) -> None:
    """The shapes of the ground-truth maps; a warning when there is none."""
    g = f.get(layout.GROUND_TRUTH)
    if g is None:
        out.warn("/", "no ground truth: accuracy cannot be measured")
        return
    shape = frame_shape(f)
    hw = shape[1:3] if shape else None
    where = f"/{layout.GROUND_TRUTH}"
    check_map(f"{where}/normal", dataset(g, "normal"), hw, (3,), limits, out)
    check_map(f"{where}/mask", dataset(g, "mask"), hw, (1,), limits, out)
    check_map(f"{where}/albedo", dataset(g, "albedo"), hw, (1, 3), limits, out)
    check_map(f"{where}/depth", dataset(g, "depth"), hw, (1,), limits, out)
    mats = g.get(layout.MATERIALS)
    for key in mats or ():
        check_map(f"{where}/{layout.MATERIALS}/{key}", dataset(mats, key), hw, (1, 3), limits, out)


def check_results(f: h5py.File, limits: Limits, out: Findings) -> None:
    """Every stored result: a normal map and the attributes that say how it was made."""
    shape = frame_shape(f)
    hw = shape[1:3] if shape else None
    for name, g in f.get(layout.RESULTS, {}).items():
        where = f"/{layout.RESULTS}/{name}"
        normal = dataset(g, "normal")
        if normal is None:
            out.error(where, "dataset 'normal' is missing")
        else:
            check_map(f"{where}/normal", normal, hw, (3,), limits, out)
        values = attrs(g, (*layout.RESULT_ATTRS, "data_rate"))
        for key in ("solver", "options"):
            if key not in values:
                out.warn(where, f"attribute {key!r} is missing")
        if "options" in values:
            try:
                options = json.loads(values["options"]) if isinstance(values["options"], str) else None
            except (ValueError, RecursionError):
                options = None
            if not isinstance(options, dict):
                out.error(where, "attribute 'options' is not a JSON object")
        for key in ("seconds", "data_rate"):
            if key in values and not is_number(values[key]):
                out.error(where, f"attribute {key!r} must be a number, got {values[key]!r}")


def scan_normals(where: str, g: h5py.Group, out: Findings) -> None:
    """The normal map of the group ``g`` (at ``where``): finite, and unit length inside its mask (a warning when not)."""
    normal = g["normal"][()].astype(np.float64)
    if not np.all(np.isfinite(normal)):
        out.error(f"{where}/normal", "holds NaN or infinite values")
        return
    mask = g["mask"][()].astype(bool) if "mask" in g and g["mask"].shape == normal.shape[:2] else np.ones(normal.shape[:2], bool)
    norms = np.linalg.norm(normal[mask], axis=-1)
    worst = float(np.max(np.abs(norms - 1.0))) if norms.size else 0.0
    if worst > NORMAL_UNIT_TOLERANCE:
        out.warn(f"{where}/normal", f"normals inside the mask are not unit length (off by up to {worst:.3g})")
