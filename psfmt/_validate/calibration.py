"""Checks of ``/calibration``: the event→frame affine, view direction, camera model (with a perspective
camera's intrinsics) and sensor constants."""

from __future__ import annotations

import h5py
import numpy as np

from psfmt import layout
from psfmt._validate.findings import Findings
from psfmt._validate.values import dataset, is_number
from psfmt.attributes import attr
from psfmt.camera import CAMERA_MODELS, INTRINSICS_SHAPE, ORTHOGRAPHIC, PERSPECTIVE, PERSPECTIVE_SINCE, intrinsics_problem
from psfmt.model import REFRACTORY_RULES
from psfmt.version import FORMAT_VERSION, FORMAT_VERSION_STR, parse_version


def check_calibration(f: h5py.File, out: Findings) -> None:
    """The structure of ``/calibration``; warnings where a hybrid capture leaves something to defaults."""
    g = f.get(layout.CALIBRATION)
    where = f"/{layout.CALIBRATION}"
    if g is None:
        if layout.EVENTS in f and layout.FRAMES in f:
            out.warn("/", "no calibration: the event→frame mapping is assumed to be a pure scale")
        return
    a = dataset(g, "event_to_frame")
    if a is not None:
        if a.shape != (2, 3):
            out.error(f"{where}/event_to_frame", f"has shape {a.shape}, expected (2, 3)")
        elif not np.all(np.isfinite(a[()])):
            out.error(f"{where}/event_to_frame", "holds NaN or infinite values")
    elif layout.EVENTS in f and layout.FRAMES in f:
        out.warn(where, "no event_to_frame affine: readers assume both cameras share the field of view")
    view = dataset(g, "view_direction")
    if view is not None:
        if view.shape != (3,):
            out.error(f"{where}/view_direction", f"has shape {view.shape}, expected (3,)")
        elif not np.all(np.isfinite(view[()])):
            out.error(f"{where}/view_direction", "holds NaN or infinite values")
    check_camera(f, g, out)
    for key in ("contrast_pos", "contrast_neg"):
        value = attr(g, key)
        if value is not None and not (is_number(value) and value > 0):
            out.error(where, f"{key} must be positive, got {value!r}")
    refractory = attr(g, "refractory_us")
    if refractory is not None and not (is_number(refractory) and refractory >= 0):
        out.error(where, f"refractory_us must be non-negative, got {refractory!r}")
    rule = attr(g, "refractory_rule")
    if rule is not None and not (isinstance(rule, str) and rule in REFRACTORY_RULES):
        out.error(where, f"refractory_rule {rule!r} is not one of {', '.join(REFRACTORY_RULES)}")
    if layout.EVENTS in f and attr(g, "contrast_pos") is None:
        out.warn(where, "contrast thresholds are unknown; solvers fall back to their defaults")
    check_sensor_model(g, out)


def check_sensor_model(g: h5py.Group, out: Findings) -> None:
    """The optional sensor-model attributes (spec §9.2): a string name, and figures that are finite
    numbers ≥ 0, only beside a name."""
    where = f"/{layout.CALIBRATION}"
    name = attr(g, layout.SENSOR_MODEL_NAME)
    if name is not None and not isinstance(name, str):
        out.error(where, f"{layout.SENSOR_MODEL_NAME} must be a string, got {name!r}")
    for key in layout.SENSOR_MODEL_FIGURES:
        value = attr(g, key)
        if value is None:
            continue
        if not (is_number(value) and value >= 0) or (key == "hot_pixel_fraction" and value > 1):
            bound = "between 0 and 1" if key == "hot_pixel_fraction" else "≥ 0"
            out.error(where, f"{key} must be a finite number {bound}, got {value!r}")
        elif name is None:
            out.error(where, f"{key} is a sensor-model figure without {layout.SENSOR_MODEL_NAME}")


def file_version(f: h5py.File) -> tuple[int, int]:
    """The file's ``format_version`` (the root check has found it readable), this reader's when it is not."""
    try:
        return parse_version(attr(f, "format_version"))
    except (ValueError, TypeError):
        return FORMAT_VERSION


def check_camera(f: h5py.File, g: h5py.Group, out: Findings) -> None:
    """``camera_model`` and ``intrinsics`` (spec §9.1). Before format 1.2 the camera is orthographic and
    ``intrinsics`` is no part of the format (ignored, as the reader ignores it); from 1.2 on, a
    perspective camera needs a valid float64 (3, 3) ``intrinsics`` and an orthographic one has none.
    The dataset's shape and dtype are checked before its 72 bytes are read."""
    where = f"/{layout.CALIBRATION}"
    model = attr(g, "camera_model")
    version = file_version(f)
    if model is not None and not (isinstance(model, str) and model in CAMERA_MODELS):
        out.error(where, f"camera_model {model!r} is not defined in format {FORMAT_VERSION_STR}")
        return
    if model == PERSPECTIVE and version < PERSPECTIVE_SINCE:
        since = ".".join(map(str, PERSPECTIVE_SINCE))
        out.error(where, f"camera_model 'perspective' needs format {since} or later, but the file is format {version[0]}.{version[1]}")
        return
    if version < PERSPECTIVE_SINCE:
        return
    k = dataset(g, "intrinsics")
    if model != PERSPECTIVE:
        if "intrinsics" in g:
            out.error(f"{where}/intrinsics", f"is given, but camera_model is {model or ORTHOGRAPHIC!r}: only a perspective camera has intrinsics")
        return
    if k is None and "intrinsics" in g:
        out.error(f"{where}/intrinsics", f"must be a dataset {INTRINSICS_SHAPE} float64")
    elif k is None:
        out.error(where, "camera_model 'perspective' needs the dataset 'intrinsics' (3, 3) float64, which is missing")
    elif k.shape != INTRINSICS_SHAPE or k.dtype.kind != "f" or k.dtype.itemsize != 8:
        out.error(f"{where}/intrinsics", f"has shape {k.shape} and dtype {k.dtype}, expected {INTRINSICS_SHAPE} float64")
    else:
        problem = intrinsics_problem(k[()])
        if problem is not None:
            out.error(f"{where}/intrinsics", problem)
