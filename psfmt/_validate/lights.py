"""Checks of ``/lights``: the light model's name and the parameters each built-in model needs."""

from __future__ import annotations

import h5py
import numpy as np

from psfmt import layout
from psfmt._validate.findings import Findings
from psfmt._validate.values import check_time, dataset, is_number
from psfmt.attributes import attr, attrs
from psfmt.version import FORMAT_VERSION_STR

UNIT_TOLERANCE = 1e-3
SAMPLED_INTERPOLATION = "linear-renormalised"
TIME_PARAMS = ("t0_us", "period_us")

# Parameters each built-in light model needs: name → expected shape (() for a scalar attribute).
LIGHT_MODEL_PARAMS: dict[str, dict[str, tuple[int, ...]]] = {
    "ring": {"elevation_deg": (), "period_us": (), "phase_deg": (), "sense": (), "intensity": (3,)},
    "sampled": {"times_us": (-1,), "directions": (-1, 3), "intensities": (-1, 3), "periodic": ()},
    "near-ring": {
        "radius_mm": (),
        "height_mm": (),
        "pixel_pitch_mm": (),
        "period_us": (),
        "phase_deg": (),
        "sense": (),
        "intensity": (3,),
    },
}


def check_params(where: str, group: h5py.Group, required: dict[str, tuple[int, ...]], out: Findings) -> None:
    """Each ``required`` parameter is present: a number for shape (), else a dataset of that shape (-1: any length)."""
    for key, shape in required.items():
        if shape == ():
            value = attr(group, key)
            if value is None:
                out.error(where, f"parameter {key!r} is missing")
            elif not (isinstance(value, bool) or is_number(value)):
                out.error(where, f"parameter {key!r} must be a number, got {value!r}")
            continue
        ds = dataset(group, key)
        if ds is None:
            out.error(where, f"parameter {key!r} is missing")
        elif len(ds.shape) != len(shape) or any(s not in (-1, d) for s, d in zip(shape, ds.shape)):
            out.error(f"{where}/{key}", f"has shape {ds.shape}, expected {tuple('M' if s < 0 else s for s in shape)}")


def check_lights(f: h5py.File, out: Findings) -> None:
    """The structure of ``/lights``: a model name, its parameters, times within range, period and sense."""
    g = f[layout.LIGHTS]
    where = f"/{layout.LIGHTS}"
    # the reader passes every attribute to the model: each is read here
    params = attrs(g)
    model = params.get("model")
    if not isinstance(model, str) or not model:
        out.error(where, "attribute 'model' is missing")
        return
    for key in TIME_PARAMS:
        if is_number(params.get(key)) and not check_time(where, params[key], out, key):
            return
    required = LIGHT_MODEL_PARAMS.get(model)
    if required is None:
        out.warn(where, f"light model {model!r} is not built in; a plugin must provide it")
        return
    before = len(out)
    check_params(where, g, required, out)
    if model == "sampled" and len(out) == before:
        m = {g[k].shape[0] for k in ("times_us", "directions", "intensities")}
        if len(m) > 1:
            out.error(where, "times_us, directions and intensities differ in length")
        if attr(g, "periodic") and "period_us" not in g.attrs:
            out.error(where, "a periodic sampled trajectory needs 'period_us'")
        if "periodic" in g.attrs and not attr(g, "periodic") and "period_us" in g.attrs:
            out.error(where, "a non-periodic sampled trajectory must not have 'period_us'")
        rule = attr(g, "interpolation")
        if rule not in (None, SAMPLED_INTERPOLATION):
            out.error(where, f"interpolation {rule!r} is not defined in format {FORMAT_VERSION_STR} (only {SAMPLED_INTERPOLATION!r})")
    for key in ("period_us",):
        value = attr(g, key)
        if value is not None and not (is_number(value) and value > 0):
            out.error(where, f"{key} must be positive, got {value!r}")
    sense = attr(g, "sense")
    if sense is not None and sense not in (1, -1):
        out.error(where, f"sense must be +1 or -1, got {sense!r}")


def scan_lights(g: h5py.Group, out: Findings) -> None:
    """The samples of a ``sampled`` model in the group ``g``: times within range and increasing,
    spanning less than a period, and unit directions (a warning when not)."""
    if attr(g, "model") != "sampled" or "directions" not in g or "times_us" not in g:
        return
    times = g["times_us"][()]
    if times.size and not all(check_time(f"/{layout.LIGHTS}/times_us", int(v), out) for v in (times.min(), times.max())):
        return
    if np.any(np.diff(times) <= 0):
        out.error(f"/{layout.LIGHTS}/times_us", "sample times are not strictly increasing")
    period = attr(g, "period_us")
    if attr(g, "periodic") and is_number(period) and times.size and times[-1] - times[0] >= period:
        out.error(f"/{layout.LIGHTS}/times_us", f"samples span {int(times[-1] - times[0])} µs, not less than period_us {period}")
    norms = np.linalg.norm(g["directions"][()], axis=-1)
    worst = float(np.max(np.abs(norms - 1.0))) if norms.size else 0.0
    if worst > UNIT_TOLERANCE:
        out.warn(f"/{layout.LIGHTS}/directions", f"directions are not unit vectors (off by up to {worst:.3g})")
