"""Two-tier validation of hybrid-capture files: errors (spec violations) and warnings (best practice).

``structure_findings`` looks at metadata and shapes only and is what the reader refuses a file on;
``content_findings`` scans the data in bounded memory (sortedness, ranges, finiteness, the index).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from psfmt import layout
from psfmt.errors import FormatError
from psfmt.files import damaged, open_hdf5
from psfmt.events import EVENT_DTYPES, MsIndexBuilder, ms_index_length
from psfmt.model import COLOR_ORDERS, FRAME_DTYPES, REFRACTORY_RULES
from psfmt.version import FORMAT_NAME, FORMAT_VERSION, FORMAT_VERSION_STR, parse_version

UNIT_TOLERANCE = 1e-3
NORMAL_UNIT_TOLERANCE = 1e-2
SATURATED_SHARE_WARNING = 0.05
SCAN_CHUNK = 1 << 21
SAMPLED_INTERPOLATION = "linear-renormalised"

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


@dataclass
class Finding:
    """One problem: ``level`` is ``error`` or ``warning``; ``where`` the HDF5 path it concerns."""

    level: str
    where: str
    message: str
    fatal: bool = False

    @property
    def text(self) -> str:
        return f"{self.where}: {self.message}"


@dataclass
class ValidationReport:
    path: Path
    errors: list[Finding] = field(default_factory=list)
    warnings: list[Finding] = field(default_factory=list)

    @property
    def valid(self) -> bool:
        return not self.errors


class _Collector(list):  # type: ignore[type-arg]
    def error(self, where: str, message: str) -> None:
        self.append(Finding("error", where, message))

    def warn(self, where: str, message: str) -> None:
        self.append(Finding("warning", where, message))

    def fatal(self, where: str, message: str) -> None:
        """The file is not a readable capture at all: nothing else is worth checking."""
        self.append(Finding("error", where, message, fatal=True))


def _attr(obj: Any, key: str) -> Any:
    value = obj.attrs.get(key)
    if isinstance(value, bytes):
        return value.decode()
    if isinstance(value, np.generic):
        return value.item()
    return value


def _dataset(group: h5py.Group, key: str) -> h5py.Dataset | None:
    obj = group.get(key)
    return obj if isinstance(obj, h5py.Dataset) else None


def _check_root(f: h5py.File, out: _Collector) -> None:
    fmt = _attr(f, "format")
    if fmt != FORMAT_NAME:
        out.fatal("/", f"not a {FORMAT_NAME} file (root attribute 'format' is {fmt!r})")
        return
    text = _attr(f, "format_version")
    try:
        version = parse_version(text)
    except ValueError:
        out.fatal("/", f"format_version {text!r} is not MAJOR.MINOR")
        return
    if version[0] > FORMAT_VERSION[0]:
        out.fatal("/", f"format_version {text} is newer than this reader supports ({FORMAT_VERSION[0]}.x); update psfmt")
    elif version[0] < FORMAT_VERSION[0]:
        out.fatal("/", f"format_version {text} predates {FORMAT_VERSION_STR} and is not supported")
    elif version[1] > FORMAT_VERSION[1]:
        out.warn("/", f"written by format {text}, newer than {FORMAT_VERSION_STR}: parts this reader does not know are ignored")
    for key in ("creator", "created"):
        if _attr(f, key) is None:
            out.warn("/", f"root attribute {key!r} is missing")
    if layout.FRAMES not in f and layout.EVENTS not in f:
        out.error("/", "the capture holds neither frames nor events")


def _frame_shape(f: h5py.File) -> tuple[int, ...] | None:
    ds = _dataset(f[layout.FRAMES], "data") if layout.FRAMES in f else None
    return tuple(ds.shape) if ds is not None and ds.ndim == 4 else None


def _check_frames(f: h5py.File, out: _Collector) -> None:
    g = f[layout.FRAMES]
    where = f"/{layout.FRAMES}"
    ds = _dataset(g, "data")
    if ds is None:
        out.error(where, "dataset 'data' is missing")
        return
    if ds.ndim != 4:
        out.error(f"{where}/data", f"has shape {ds.shape}, expected (K, H, W, C)")
        return
    k, _, _, c = ds.shape
    if ds.dtype not in FRAME_DTYPES:
        out.error(f"{where}/data", f"has dtype {ds.dtype}, expected uint8, uint16 or float32")
    if k == 0:
        out.error(f"{where}/data", "holds no frames")
    order = _attr(g, "color_order")
    if order not in COLOR_ORDERS:
        out.error(where, f"color_order {order!r} is not one of {sorted(COLOR_ORDERS)}")
    elif COLOR_ORDERS[order] != c:
        out.error(where, f"color_order {order!r} does not fit {c} channels")
    saturation = _attr(g, "saturation")
    if not isinstance(saturation, (int, float)) or not np.isfinite(saturation) or saturation <= 0:
        out.error(where, f"saturation {saturation!r} must be a positive number")
    bits = _attr(g, "bit_depth")
    if not isinstance(bits, int) or not 1 <= bits <= ds.dtype.itemsize * 8:
        out.error(where, f"bit_depth {bits!r} does not fit dtype {ds.dtype}")
    if _attr(g, "response") != "linear":
        out.error(where, f"response {_attr(g, 'response')!r} is not 'linear'")
    windows = [key for key in layout.FRAME_WINDOW if key in g]
    if len(windows) == 1:
        out.error(where, f"{windows[0]} is given without its partner")
    for key in layout.FRAME_WINDOW:
        if key in g:
            w = g[key]
            if w.shape != (k,) or w.dtype.kind not in "iu":
                out.error(f"{where}/{key}", f"has shape {w.shape} and dtype {w.dtype}, expected ({k},) int64")
                return
    if len(windows) == 2:
        start, end = g["t_start_us"][()], g["t_end_us"][()]
        bad = np.flatnonzero(end <= start)
        if bad.size:
            out.error(where, f"exposure window of frame {bad[0]} ends before it starts")
    for key in layout.FRAME_INSTANT:
        if key in g and g[key].shape != (k, 3):
            out.error(f"{where}/{key}", f"has shape {g[key].shape}, expected ({k}, 3)")
    if "light_intensity" in g and "light_direction" not in g:
        out.error(where, "light_intensity is given without light_direction")
    if not windows and "light_direction" not in g:
        out.error(where, "frames need exposure windows (t_start_us, t_end_us) or per-frame light_direction")


def _check_events(f: h5py.File, out: _Collector) -> None:
    g = f[layout.EVENTS]
    where = f"/{layout.EVENTS}"
    for key in ("width", "height"):
        value = _attr(g, key)
        if not isinstance(value, int) or value <= 0:
            out.error(where, f"attribute {key!r} must be a positive integer, got {value!r}")
    lengths = set()
    for c, dtype in EVENT_DTYPES.items():
        ds = _dataset(g, c)
        if ds is None:
            out.error(where, f"dataset {c!r} is missing")
            continue
        if ds.ndim != 1:
            out.error(f"{where}/{c}", f"has shape {ds.shape}, expected 1-D")
        if ds.dtype != dtype:
            out.error(f"{where}/{c}", f"has dtype {ds.dtype}, expected {dtype}")
        lengths.add(ds.shape[0] if ds.ndim else -1)
    if len(lengths) > 1:
        out.error(where, f"columns x, y, t, p differ in length ({sorted(lengths)})")
        return
    index = _dataset(g, "ms_to_idx")
    if index is None or "ms_origin_us" not in g.attrs:
        out.error(where, "the millisecond index (ms_to_idx, ms_origin_us) is missing")
    elif "t" in g and lengths:
        n = lengths.pop()
        t = g["t"]
        first, last = (int(t[0]), int(t[n - 1])) if n > 0 else (None, None)
        expected = ms_index_length(first, last)
        if index.shape != (expected,):
            out.error(f"{where}/ms_to_idx", f"has shape {index.shape}, expected ({expected},) for the stored times")


def _check_params(where: str, group: h5py.Group, required: dict[str, tuple[int, ...]], out: _Collector) -> None:
    for key, shape in required.items():
        if shape == ():
            if key not in group.attrs:
                out.error(where, f"parameter {key!r} is missing")
            continue
        ds = _dataset(group, key)
        if ds is None:
            out.error(where, f"parameter {key!r} is missing")
        elif len(ds.shape) != len(shape) or any(s not in (-1, d) for s, d in zip(shape, ds.shape)):
            out.error(f"{where}/{key}", f"has shape {ds.shape}, expected {tuple('M' if s < 0 else s for s in shape)}")


def _check_lights(f: h5py.File, out: _Collector) -> None:
    g = f[layout.LIGHTS]
    where = f"/{layout.LIGHTS}"
    model = _attr(g, "model")
    if not isinstance(model, str) or not model:
        out.error(where, "attribute 'model' is missing")
        return
    required = LIGHT_MODEL_PARAMS.get(model)
    if required is None:
        out.warn(where, f"light model {model!r} is not built in; a plugin must provide it")
        return
    _check_params(where, g, required, out)
    if model == "sampled":
        m = {g[k].shape[0] for k in ("times_us", "directions", "intensities") if k in g}
        if len(m) > 1:
            out.error(where, "times_us, directions and intensities differ in length")
        if _attr(g, "periodic") and "period_us" not in g.attrs:
            out.error(where, "a periodic sampled trajectory needs 'period_us'")
        if "periodic" in g.attrs and not _attr(g, "periodic") and "period_us" in g.attrs:
            out.error(where, "a non-periodic sampled trajectory must not have 'period_us'")
        rule = _attr(g, "interpolation")
        if rule not in (None, SAMPLED_INTERPOLATION):
            out.error(where, f"interpolation {rule!r} is not defined in format {FORMAT_VERSION_STR} (only {SAMPLED_INTERPOLATION!r})")
    for key in ("period_us",):
        value = _attr(g, key)
        if value is not None and not (isinstance(value, (int, float)) and value > 0):
            out.error(where, f"{key} must be positive, got {value!r}")
    sense = _attr(g, "sense")
    if sense is not None and sense not in (1, -1):
        out.error(where, f"sense must be +1 or -1, got {sense!r}")


def _check_calibration(f: h5py.File, out: _Collector) -> None:
    g = f.get(layout.CALIBRATION)
    where = f"/{layout.CALIBRATION}"
    if g is None:
        if layout.EVENTS in f and layout.FRAMES in f:
            out.warn("/", "no calibration: the event→frame mapping is assumed to be a pure scale")
        return
    if "event_to_frame" in g:
        a = g["event_to_frame"]
        if a.shape != (2, 3):
            out.error(f"{where}/event_to_frame", f"has shape {a.shape}, expected (2, 3)")
        elif not np.all(np.isfinite(a[()])):
            out.error(f"{where}/event_to_frame", "holds NaN or infinite values")
    elif layout.EVENTS in f and layout.FRAMES in f:
        out.warn(where, "no event_to_frame affine: readers assume both cameras share the field of view")
    if "view_direction" in g and g["view_direction"].shape != (3,):
        out.error(f"{where}/view_direction", f"has shape {g['view_direction'].shape}, expected (3,)")
    model = _attr(g, "camera_model")
    if model not in (None, "orthographic"):
        out.error(where, f"camera_model {model!r} is not defined in format {FORMAT_VERSION_STR}")
    for key in ("contrast_pos", "contrast_neg"):
        value = _attr(g, key)
        if value is not None and not (isinstance(value, (int, float)) and value > 0):
            out.error(where, f"{key} must be positive, got {value!r}")
    refractory = _attr(g, "refractory_us")
    if refractory is not None and not (isinstance(refractory, (int, float)) and refractory >= 0):
        out.error(where, f"refractory_us must be non-negative, got {refractory!r}")
    rule = _attr(g, "refractory_rule")
    if rule is not None and rule not in REFRACTORY_RULES:
        out.error(where, f"refractory_rule {rule!r} is not one of {', '.join(REFRACTORY_RULES)}")
    if layout.EVENTS in f and _attr(g, "contrast_pos") is None:
        out.warn(where, "contrast thresholds are unknown; solvers fall back to their defaults")


def _check_map(where: str, ds: h5py.Dataset | None, hw: tuple[int, int] | None, channels: tuple[int, ...], out: _Collector) -> None:
    if ds is None:
        return
    shapes_ok = (ds.ndim == 2 and 1 in channels) or (ds.ndim == 3 and ds.shape[2] in channels)
    if not shapes_ok:
        out.error(where, f"has shape {ds.shape}, expected (H, W{', C' if channels != (1,) else ''})")
    elif hw is not None and tuple(ds.shape[:2]) != hw:
        out.error(where, f"is {ds.shape[0]}×{ds.shape[1]}, but the frames are {hw[0]}×{hw[1]}")


def _check_ground_truth(f: h5py.File, out: _Collector) -> None:
    g = f.get(layout.GROUND_TRUTH)
    if g is None:
        out.warn("/", "no ground truth: accuracy cannot be measured")
        return
    shape = _frame_shape(f)
    hw = shape[1:3] if shape else None
    where = f"/{layout.GROUND_TRUTH}"
    _check_map(f"{where}/normal", _dataset(g, "normal"), hw, (3,), out)
    _check_map(f"{where}/mask", _dataset(g, "mask"), hw, (1,), out)
    _check_map(f"{where}/albedo", _dataset(g, "albedo"), hw, (1, 3), out)
    _check_map(f"{where}/depth", _dataset(g, "depth"), hw, (1,), out)
    mats = g.get(layout.MATERIALS)
    for key in mats or ():
        _check_map(f"{where}/{layout.MATERIALS}/{key}", _dataset(mats, key), hw, (1, 3), out)


def _check_results(f: h5py.File, out: _Collector) -> None:
    shape = _frame_shape(f)
    hw = shape[1:3] if shape else None
    for name, g in f.get(layout.RESULTS, {}).items():
        where = f"/{layout.RESULTS}/{name}"
        if "normal" not in g:
            out.error(where, "dataset 'normal' is missing")
        else:
            _check_map(f"{where}/normal", g["normal"], hw, (3,), out)
        for key in ("solver", "options"):
            if key not in g.attrs:
                out.warn(where, f"attribute {key!r} is missing")


def _check_ratio(f: h5py.File, out: _Collector) -> None:
    shape = _frame_shape(f)
    g = f.get(layout.EVENTS)
    if shape is None or g is None:
        return
    w, h = _attr(g, "width"), _attr(g, "height")
    if not isinstance(w, int) or not isinstance(h, int) or w <= 0 or h <= 0:
        return
    rx, ry = shape[2] / w, shape[1] / h
    if not 0.99 <= rx <= 16 or abs(rx - ry) > 0.02 * rx:
        out.warn("/", f"unusual frame/event resolution ratio {rx:.2f}×{ry:.2f} (expected equal, between 1 and 16)")


def structure_findings(f: h5py.File) -> list[Finding]:
    """Findings from metadata and shapes alone (cheap: no data scan)."""
    out = _Collector()
    _check_root(f, out)
    if any(x.fatal for x in out):
        return list(out)
    checks = (
        (layout.FRAMES, _check_frames),
        (layout.EVENTS, _check_events),
        (layout.LIGHTS, _check_lights),
    )
    for name, check in checks:
        if name in f:
            if not isinstance(f[name], h5py.Group):
                out.error(f"/{name}", "must be a group")
            else:
                check(f, out)
    frames = f.get(layout.FRAMES)
    instant = isinstance(frames, h5py.Group) and "light_direction" in frames
    if layout.LIGHTS not in f and not instant:
        out.warn("/", "no light model: solvers cannot use this capture without one")
    _check_calibration(f, out)
    _check_ground_truth(f, out)
    _check_results(f, out)
    _check_ratio(f, out)
    return list(out)


def _scan_events(g: h5py.Group, out: _Collector) -> None:
    where = f"/{layout.EVENTS}"
    width, height = _attr(g, "width"), _attr(g, "height")
    n = g["t"].shape[0]
    builder = MsIndexBuilder()
    previous = None
    for start in range(0, n, SCAN_CHUNK):
        stop = min(start + SCAN_CHUNK, n)
        t = g["t"][start:stop]
        steps = np.flatnonzero(np.diff(t) < 0)
        if steps.size or (previous is not None and t[0] < previous):
            at = start + int(steps[0]) + 1 if steps.size else start
            out.error(f"{where}/t", f"events are not sorted by time (event {at} goes back)")
            return
        previous = int(t[-1])
        builder.add(t)
        p = g["p"][start:stop]
        bad = np.flatnonzero((p != 1) & (p != -1))
        if bad.size:
            out.error(f"{where}/p", f"polarity of event {start + int(bad[0])} is {int(p[bad[0]])}, not ±1")
            return
        for c, limit in (("x", width), ("y", height)):
            col = g[c][start:stop]
            bad = np.flatnonzero(col >= limit)
            if bad.size:
                out.error(f"{where}/{c}", f"event {start + int(bad[0])} has {c} = {int(col[bad[0]])}, outside the {width}×{height} sensor")
                return
    stored = g["ms_to_idx"][()]
    expected = builder.finish()
    origin = _attr(g, "ms_origin_us")
    if origin != builder.origin_us or stored.shape != expected.shape or not np.array_equal(stored, expected):
        out.error(f"{where}/ms_to_idx", "does not match the event times (rebuild the index)")


def _scan_frames(g: h5py.Group, out: _Collector) -> None:
    ds = g["data"]
    saturation = float(_attr(g, "saturation"))
    saturated = 0
    for k in range(ds.shape[0]):
        frame = ds[k]
        if ds.dtype.kind == "f" and not np.all(np.isfinite(frame)):
            out.error(f"/{layout.FRAMES}/data", f"frame {k} holds NaN or infinite values")
            return
        saturated += int(np.count_nonzero(frame >= saturation))
    share = saturated / max(1, ds.size)
    if share > SATURATED_SHARE_WARNING:
        out.warn(f"/{layout.FRAMES}/data", f"{100 * share:.1f} % of the pixel values are saturated")


def _scan_lights(g: h5py.Group, out: _Collector) -> None:
    if _attr(g, "model") != "sampled" or "directions" not in g or "times_us" not in g:
        return
    times = g["times_us"][()]
    if np.any(np.diff(times) <= 0):
        out.error(f"/{layout.LIGHTS}/times_us", "sample times are not strictly increasing")
    period = _attr(g, "period_us")
    if _attr(g, "periodic") and isinstance(period, (int, float)) and times.size and times[-1] - times[0] >= period:
        out.error(f"/{layout.LIGHTS}/times_us", f"samples span {int(times[-1] - times[0])} µs, not less than period_us {period}")
    norms = np.linalg.norm(g["directions"][()], axis=-1)
    worst = float(np.max(np.abs(norms - 1.0))) if norms.size else 0.0
    if worst > UNIT_TOLERANCE:
        out.warn(f"/{layout.LIGHTS}/directions", f"directions are not unit vectors (off by up to {worst:.3g})")


def _scan_normals(where: str, g: h5py.Group, out: _Collector) -> None:
    normal = g["normal"][()].astype(np.float64)
    if not np.all(np.isfinite(normal)):
        out.error(f"{where}/normal", "holds NaN or infinite values")
        return
    mask = g["mask"][()].astype(bool) if "mask" in g and g["mask"].shape == normal.shape[:2] else np.ones(normal.shape[:2], bool)
    norms = np.linalg.norm(normal[mask], axis=-1)
    worst = float(np.max(np.abs(norms - 1.0))) if norms.size else 0.0
    if worst > NORMAL_UNIT_TOLERANCE:
        out.warn(f"{where}/normal", f"normals inside the mask are not unit length (off by up to {worst:.3g})")


def content_findings(f: h5py.File) -> list[Finding]:
    """Findings from scanning the data in bounded memory (assumes the structure is sound)."""
    out = _Collector()
    if layout.EVENTS in f:
        _scan_events(f[layout.EVENTS], out)
    if layout.FRAMES in f:
        _scan_frames(f[layout.FRAMES], out)
    if layout.LIGHTS in f:
        _scan_lights(f[layout.LIGHTS], out)
    gt = f.get(layout.GROUND_TRUTH)
    if gt is not None and "normal" in gt and gt["normal"].ndim == 3:
        _scan_normals(f"/{layout.GROUND_TRUTH}", gt, out)
    return list(out)


def validate(path: str | os.PathLike[str]) -> ValidationReport:
    """Check a file against the spec. Raises FormatError only when it cannot be opened as HDF5 at all
    or is not a hybrid capture of a readable major version."""
    path = Path(path)
    with open_hdf5(path) as f:
        try:
            findings = structure_findings(f)
            fatal = [x for x in findings if x.fatal]
            if fatal:
                raise FormatError(path, fatal[0].text)
            if not any(x.level == "error" for x in findings):
                findings += content_findings(f)
        except OSError as exc:
            raise damaged(path, exc) from exc
    report = ValidationReport(path)
    for finding in findings:
        (report.errors if finding.level == "error" else report.warnings).append(finding)
    return report
