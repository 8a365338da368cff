"""Checks of ``/calibration``: the event→frame affine, view direction, camera model and sensor constants."""

from __future__ import annotations

import h5py
import numpy as np

from psfmt import layout
from psfmt._validate.findings import Findings
from psfmt._validate.values import dataset, is_number
from psfmt.attributes import attr
from psfmt.model import REFRACTORY_RULES
from psfmt.version import FORMAT_VERSION_STR


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
    model = attr(g, "camera_model")
    if model not in (None, "orthographic"):
        out.error(where, f"camera_model {model!r} is not defined in format {FORMAT_VERSION_STR}")
    for key in ("contrast_pos", "contrast_neg"):
        value = attr(g, key)
        if value is not None and not (is_number(value) and value > 0):
            out.error(where, f"{key} must be positive, got {value!r}")
    refractory = attr(g, "refractory_us")
    if refractory is not None and not (is_number(refractory) and refractory >= 0):
        out.error(where, f"refractory_us must be non-negative, got {refractory!r}")
    rule = attr(g, "refractory_rule")
    if rule is not None and rule not in REFRACTORY_RULES:
        out.error(where, f"refractory_rule {rule!r} is not one of {', '.join(REFRACTORY_RULES)}")
    if layout.EVENTS in f and attr(g, "contrast_pos") is None:
        out.warn(where, "contrast thresholds are unknown; solvers fall back to their defaults")
