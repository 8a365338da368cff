"""Two-tier validation of hybrid-capture files: errors (spec violations) and warnings (best practice).

``inspect`` is the one set of checks the validator and the reader share, so they agree on every
file. ``structure_findings`` looks at metadata, shapes and storage only (what the reader refuses a
file on): before anything is read, every dataset's declared size is held against what the file
stores and against ``psfmt.Limits``, and links, external storage and filters that would read other
files or inflate without bound are refused. ``content_findings`` then reads every dataset a reader
may read, block by block in bounded memory (sortedness, ranges, finiteness, the index), so a file
that validates also reads.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from psfmt import isolate, layout
from psfmt.errors import FormatError
from psfmt.events import EVENT_DTYPES, MsIndexBuilder, ms_index_length
from psfmt.files import hdf5_errors, open_hdf5
from psfmt.limits import DEFLATE_MAX_RATIO, FILL_ALLOWANCE, MAX_ABS_TIME_US, MAX_SENSOR_SIDE, Limits
from psfmt.model import COLOR_ORDERS, FRAME_DTYPES, REFRACTORY_RULES
from psfmt.version import FORMAT_NAME, FORMAT_VERSION, FORMAT_VERSION_STR, parse_version

Progress = Callable[[float, str], None]
"""``progress(fraction, message)``: how far a content scan is, 0…1."""

UNIT_TOLERANCE = 1e-3
NORMAL_UNIT_TOLERANCE = 1e-2
SATURATED_SHARE_WARNING = 0.05
SCAN_CHUNK = 1 << 21
SCAN_BYTES = 1 << 24
"""Bytes of one block a content scan reads (events: ``SCAN_CHUNK`` rows of every column)."""
SAMPLED_INTERPOLATION = "linear-renormalised"
ALLOWED_FILTERS = {1: "deflate", 2: "shuffle", 3: "fletcher32"}
TRIGGER_DTYPES: dict[str, np.dtype[Any]] = {"t": np.dtype(np.int64), "channel": np.dtype(np.uint8), "value": np.dtype(np.int8)}
KNOWN_GROUPS = (
    layout.FRAMES,
    layout.EVENTS,
    layout.TRIGGERS,
    layout.LIGHTS,
    layout.CALIBRATION,
    layout.GROUND_TRUTH,
    layout.RESULTS,
)
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

    @property
    def failed(self) -> bool:
        return any(x.level == "error" for x in self)


def plain(value: Any) -> Any:
    """An HDF5 attribute value as plain Python (str, int, float, bool) or a numpy array; bytes are
    decoded as UTF-8 with undecodable bytes replaced."""
    if isinstance(value, bytes):
        return value.decode("utf-8", errors="replace")
    if isinstance(value, np.generic):
        return value.item()
    return value


def attr(obj: Any, key: str) -> Any:
    """Attribute ``key`` of ``obj`` as a plain value, None when it is absent. A damaged attribute raises
    (h5py's error), never reads as absent: the reader and the validator both read through here."""
    return plain(obj.attrs[key]) if key in obj.attrs else None


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _dataset(group: h5py.Group, key: str) -> h5py.Dataset | None:
    obj = group.get(key)
    return obj if isinstance(obj, h5py.Dataset) else None


def _size(shape: tuple[int, ...]) -> int:
    return math.prod(int(d) for d in shape)


def _check_root(f: h5py.File, out: _Collector) -> None:
    fmt = attr(f, "format")
    if fmt != FORMAT_NAME:
        out.fatal("/", f"not a {FORMAT_NAME} file (root attribute 'format' is {fmt!r})")
        return
    text = attr(f, "format_version")
    try:
        version = parse_version(text)
    except (ValueError, TypeError):
        out.fatal("/", f"format_version {text!r} is not MAJOR.MINOR")
        return
    if version[0] > FORMAT_VERSION[0]:
        out.fatal("/", f"format_version {text} is newer than this reader supports ({FORMAT_VERSION[0]}.x); update psfmt")
    elif version[0] < FORMAT_VERSION[0]:
        out.fatal("/", f"format_version {text} predates {FORMAT_VERSION_STR} and is not supported")
    elif version[1] > FORMAT_VERSION[1]:
        out.warn("/", f"written by format {text}, newer than {FORMAT_VERSION_STR}: parts this reader does not know are ignored")
    # the reader takes every root attribute of the format: each is read here, so a damaged one shows now
    values = {key: attr(f, key) for key in layout.ROOT_ATTRS}
    for key in ("creator", "created"):
        if values[key] is None:
            out.warn("/", f"root attribute {key!r} is missing")
    if layout.FRAMES not in f and layout.EVENTS not in f:
        out.error("/", "the capture holds neither frames nor events")


# storage -------------------------------------------------------------------------------------------

def _check_dataset(where: str, ds: h5py.Dataset, file_bytes: int, limits: Limits, out: _Collector, *, whole: bool = True) -> None:
    """A dataset's storage before any of it is read: no virtual or external data (other files), only
    the format's filters, numbers, and a declared size the stored bytes can hold (at most
    ``DEFLATE_MAX_RATIO`` times them once inflated) within the limits. ``whole``: a reader reads the
    dataset at once, so it must fit ``limits.max_array_bytes``."""
    plist = ds.id.get_create_plist()
    if plist.get_layout() == h5py.h5d.VIRTUAL:
        out.error(where, "is a virtual dataset: its data would come from other files, which a capture must not refer to")
        return
    if plist.get_external_count():
        out.error(where, "keeps its data in external files, which a capture must not refer to")
        return
    codes = [int(plist.get_filter(i)[0]) for i in range(plist.get_nfilters())]
    other = [c for c in codes if c not in ALLOWED_FILTERS]
    if other:
        out.error(where, f"uses HDF5 filter {other[0]}; format {FORMAT_VERSION_STR} allows only deflate (1), shuffle (2) and fletcher32 (3)")
        return
    if ds.shape is None or ds.dtype.kind not in "biuf":
        out.error(where, f"has dtype {ds.dtype}{'' if ds.shape is not None else ' and no dataspace'}, expected numbers")
        return
    itemsize = ds.dtype.itemsize
    declared = _size(ds.shape) * itemsize
    if ds.chunks is not None and _size(ds.chunks) * itemsize > limits.max_chunk_bytes:
        out.error(where, f"has chunks of {_size(ds.chunks) * itemsize:,} bytes, more than the limit of {limits.max_chunk_bytes:,} (PSFMT_MAX_CHUNK_BYTES)")
        return
    stored = int(ds.id.get_storage_size())
    if stored > file_bytes:
        out.error(where, f"claims {stored:,} bytes of storage in a file of {file_bytes:,} bytes (a damaged file)")
        return
    most = stored * (DEFLATE_MAX_RATIO if 1 in codes else 1)
    if declared > max(FILL_ALLOWANCE, most):
        held = f"stores {stored:,} bytes for it, which inflate to at most {most:,}" if stored else "stores no data for it"
        out.error(where, f"declares {ds.shape} {ds.dtype} ({declared:,} bytes) but the file {held}")
        return
    if whole and declared > limits.max_array_bytes:
        out.error(where, f"holds {declared:,} bytes, more than the limit of {limits.max_array_bytes:,} read at once (PSFMT_MAX_ARRAY_BYTES)")


def _member(group: h5py.Group, name: str, where: str, out: _Collector) -> Any:
    """The object ``group[name]`` (None when absent); an external link is reported, not followed."""
    link = group.get(name, getlink=True)
    if link is None:
        return None
    if isinstance(link, h5py.ExternalLink):
        out.error(where, "is an external link to another file, which a capture must not refer to")
        return None
    return group[name]


def _check_storage(f: h5py.File, file_bytes: int, limits: Limits, out: _Collector) -> None:
    """Every group and dataset a reader may open, before anything of them is read (see ``_check_dataset``)."""
    for name in KNOWN_GROUPS:
        where = f"/{name}"
        group = _member(f, name, where, out)
        if group is None:
            continue
        if not isinstance(group, h5py.Group):
            out.error(where, "must be a group")
            continue
        for key in group:
            path = f"{where}/{key}"
            obj = _member(group, key, path, out)
            if name == layout.RESULTS or (name == layout.GROUND_TRUTH and key == layout.MATERIALS):
                if obj is not None and not isinstance(obj, h5py.Group):
                    out.error(path, "must be a group")
                elif obj is not None:
                    for inner in obj:
                        item = _member(obj, inner, f"{path}/{inner}", out)
                        if isinstance(item, h5py.Dataset):
                            _check_dataset(f"{path}/{inner}", item, file_bytes, limits, out)
            elif isinstance(obj, h5py.Dataset):
                streamed = (name == layout.EVENTS and key in EVENT_DTYPES) or (name == layout.FRAMES and key == "data")
                _check_dataset(path, obj, file_bytes, limits, out, whole=not streamed)


def _check_pixels(where: str, height: int, width: int, limits: Limits, out: _Collector) -> bool:
    if height * width > limits.max_pixels:
        out.error(where, f"is {width}×{height} pixels, more than the limit of {limits.max_pixels:,} (PSFMT_MAX_PIXELS)")
        return False
    return True


def _check_time(where: str, value: Any, out: _Collector, what: str = "time") -> bool:
    if abs(value) > MAX_ABS_TIME_US:
        out.error(where, f"{what} {value} µs lies beyond ±2^53 µs (±285 years), where times stop converting to float64 exactly")
        return False
    return True


# structure -----------------------------------------------------------------------------------------

def _frame_shape(f: h5py.File) -> tuple[int, ...] | None:
    ds = _dataset(f[layout.FRAMES], "data") if layout.FRAMES in f else None
    return tuple(ds.shape) if ds is not None and ds.ndim == 4 else None


def _check_frames(f: h5py.File, limits: Limits, out: _Collector) -> None:
    g = f[layout.FRAMES]
    where = f"/{layout.FRAMES}"
    ds = _dataset(g, "data")
    if ds is None:
        out.error(where, "dataset 'data' is missing")
        return
    if ds.ndim != 4:
        out.error(f"{where}/data", f"has shape {ds.shape}, expected (K, H, W, C)")
        return
    k, h, w, c = ds.shape
    if ds.dtype not in FRAME_DTYPES:
        out.error(f"{where}/data", f"has dtype {ds.dtype}, expected uint8, uint16 or float32")
    if k == 0:
        out.error(f"{where}/data", "holds no frames")
    elif _check_pixels(f"{where}/data", h, w, limits, out) and h * w * c * ds.dtype.itemsize > limits.max_array_bytes:
        out.error(f"{where}/data", f"has frames of {h * w * c * ds.dtype.itemsize:,} bytes, more than the limit of {limits.max_array_bytes:,} "
                  "read at once (PSFMT_MAX_ARRAY_BYTES)")
    order = attr(g, "color_order")
    if order not in COLOR_ORDERS:
        out.error(where, f"color_order {order!r} is not one of {sorted(COLOR_ORDERS)}")
    elif COLOR_ORDERS[order] != c:
        out.error(where, f"color_order {order!r} does not fit {c} channels")
    saturation = attr(g, "saturation")
    if not _is_number(saturation) or saturation <= 0:
        out.error(where, f"saturation {saturation!r} must be a positive number")
    bits = attr(g, "bit_depth")
    if not _is_int(bits) or not 1 <= bits <= ds.dtype.itemsize * 8:
        out.error(where, f"bit_depth {bits!r} does not fit dtype {ds.dtype}")
    black = attr(g, "black_level")
    if black is not None and not _is_number(black):
        out.error(where, f"black_level {black!r} must be a number")
    if attr(g, "response") != "linear":
        out.error(where, f"response {attr(g, 'response')!r} is not 'linear'")
    windows = [key for key in layout.FRAME_WINDOW if key in g]
    if len(windows) == 1:
        out.error(where, f"{windows[0]} is given without its partner")
    for key in layout.FRAME_WINDOW:
        if key in g:
            w = _dataset(g, key)
            if w is None or w.shape != (k,) or w.dtype.kind not in "iu":
                shape, dtype = (w.shape, w.dtype) if w is not None else ("none", "none (not a dataset)")
                out.error(f"{where}/{key}", f"has shape {shape} and dtype {dtype}, expected ({k},) int64")
                return
    if len(windows) == 2:
        start, end = g["t_start_us"][()], g["t_end_us"][()]
        for key, times in (("t_start_us", start), ("t_end_us", end)):
            if times.size and not all(_check_time(f"{where}/{key}", int(v), out) for v in (times.min(), times.max())):
                return
        bad = np.flatnonzero(end.astype(np.int64) <= start.astype(np.int64))
        if bad.size:
            out.error(where, f"exposure window of frame {bad[0]} ends before it starts")
    for key in layout.FRAME_INSTANT:
        if key in g:
            instant = _dataset(g, key)
            if instant is None or instant.shape != (k, 3):
                out.error(f"{where}/{key}", f"has shape {instant.shape if instant is not None else 'none'}, expected ({k}, 3)")
    if "light_intensity" in g and "light_direction" not in g:
        out.error(where, "light_intensity is given without light_direction")
    if not windows and "light_direction" not in g:
        out.error(where, "frames need exposure windows (t_start_us, t_end_us) or per-frame light_direction")


def _check_events(f: h5py.File, limits: Limits, out: _Collector) -> None:
    g = f[layout.EVENTS]
    where = f"/{layout.EVENTS}"
    sides = {}
    for key in ("width", "height"):
        value = attr(g, key)
        if not _is_int(value) or value <= 0:
            out.error(where, f"attribute {key!r} must be a positive integer, got {value!r}")
        elif value > MAX_SENSOR_SIDE:
            out.error(where, f"{key} {value} exceeds {MAX_SENSOR_SIDE}, the most uint16 coordinates address")
        else:
            sides[key] = value
    if len(sides) == 2:
        _check_pixels(where, sides["height"], sides["width"], limits, out)
    lengths = set()
    columns_ok = True
    for c, dtype in EVENT_DTYPES.items():
        ds = _dataset(g, c)
        if ds is None:
            out.error(where, f"dataset {c!r} is missing")
            columns_ok = False
            continue
        if ds.ndim != 1:
            out.error(f"{where}/{c}", f"has shape {ds.shape}, expected 1-D")
        if ds.dtype != dtype:
            out.error(f"{where}/{c}", f"has dtype {ds.dtype}, expected {dtype}")
        columns_ok = columns_ok and ds.ndim == 1 and ds.dtype == dtype
        lengths.add(ds.shape[0] if ds.ndim else -1)
    if len(lengths) > 1:
        out.error(where, f"columns x, y, t, p differ in length ({sorted(lengths)})")
        return
    index = _dataset(g, "ms_to_idx")
    origin = attr(g, "ms_origin_us")
    if index is None or origin is None:
        out.error(where, "the millisecond index (ms_to_idx, ms_origin_us) is missing")
    elif not _is_int(origin):
        out.error(where, f"ms_origin_us {origin!r} must be an integer")
    elif _check_time(where, origin, out, "ms_origin_us") and columns_ok:
        n = lengths.pop()
        t = g["t"]
        first, last = (int(t[0]), int(t[n - 1])) if n > 0 else (None, None)
        if n > 0 and not (_check_time(f"{where}/t", first, out) and _check_time(f"{where}/t", last, out)):
            return
        expected = ms_index_length(first, last)
        if index.shape != (expected,):
            out.error(f"{where}/ms_to_idx", f"has shape {index.shape}, expected ({expected},) for the stored times")
        elif index.dtype.kind not in "iu":
            out.error(f"{where}/ms_to_idx", f"has dtype {index.dtype}, expected uint64")


def _check_triggers(f: h5py.File, out: _Collector) -> None:
    g = f[layout.TRIGGERS]
    where = f"/{layout.TRIGGERS}"
    lengths = set()
    for c, dtype in TRIGGER_DTYPES.items():
        ds = _dataset(g, c)
        if ds is None:
            out.error(where, f"dataset {c!r} is missing")
        elif ds.ndim != 1 or ds.dtype != dtype:
            out.error(f"{where}/{c}", f"has shape {ds.shape} and dtype {ds.dtype}, expected (M,) {dtype}")
        else:
            lengths.add(ds.shape[0])
    if len(lengths) > 1:
        out.error(where, f"columns t, channel, value differ in length ({sorted(lengths)})")


def _check_params(where: str, group: h5py.Group, required: dict[str, tuple[int, ...]], out: _Collector) -> None:
    for key, shape in required.items():
        if shape == ():
            value = attr(group, key)
            if value is None:
                out.error(where, f"parameter {key!r} is missing")
            elif not (isinstance(value, bool) or _is_number(value)):
                out.error(where, f"parameter {key!r} must be a number, got {value!r}")
            continue
        ds = _dataset(group, key)
        if ds is None:
            out.error(where, f"parameter {key!r} is missing")
        elif len(ds.shape) != len(shape) or any(s not in (-1, d) for s, d in zip(shape, ds.shape)):
            out.error(f"{where}/{key}", f"has shape {ds.shape}, expected {tuple('M' if s < 0 else s for s in shape)}")


def _check_lights(f: h5py.File, out: _Collector) -> None:
    g = f[layout.LIGHTS]
    where = f"/{layout.LIGHTS}"
    # the reader passes every attribute to the model: each is read here
    params = {key: plain(value) for key, value in g.attrs.items()}
    model = params.get("model")
    if not isinstance(model, str) or not model:
        out.error(where, "attribute 'model' is missing")
        return
    for key in TIME_PARAMS:
        if _is_number(params.get(key)) and not _check_time(where, params[key], out, key):
            return
    required = LIGHT_MODEL_PARAMS.get(model)
    if required is None:
        out.warn(where, f"light model {model!r} is not built in; a plugin must provide it")
        return
    before = len(out)
    _check_params(where, g, required, out)
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
        if value is not None and not (_is_number(value) and value > 0):
            out.error(where, f"{key} must be positive, got {value!r}")
    sense = attr(g, "sense")
    if sense is not None and sense not in (1, -1):
        out.error(where, f"sense must be +1 or -1, got {sense!r}")


def _check_calibration(f: h5py.File, out: _Collector) -> None:
    g = f.get(layout.CALIBRATION)
    where = f"/{layout.CALIBRATION}"
    if g is None:
        if layout.EVENTS in f and layout.FRAMES in f:
            out.warn("/", "no calibration: the event→frame mapping is assumed to be a pure scale")
        return
    a = _dataset(g, "event_to_frame")
    if a is not None:
        if a.shape != (2, 3):
            out.error(f"{where}/event_to_frame", f"has shape {a.shape}, expected (2, 3)")
        elif not np.all(np.isfinite(a[()])):
            out.error(f"{where}/event_to_frame", "holds NaN or infinite values")
    elif layout.EVENTS in f and layout.FRAMES in f:
        out.warn(where, "no event_to_frame affine: readers assume both cameras share the field of view")
    view = _dataset(g, "view_direction")
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
        if value is not None and not (_is_number(value) and value > 0):
            out.error(where, f"{key} must be positive, got {value!r}")
    refractory = attr(g, "refractory_us")
    if refractory is not None and not (_is_number(refractory) and refractory >= 0):
        out.error(where, f"refractory_us must be non-negative, got {refractory!r}")
    rule = attr(g, "refractory_rule")
    if rule is not None and rule not in REFRACTORY_RULES:
        out.error(where, f"refractory_rule {rule!r} is not one of {', '.join(REFRACTORY_RULES)}")
    if layout.EVENTS in f and attr(g, "contrast_pos") is None:
        out.warn(where, "contrast thresholds are unknown; solvers fall back to their defaults")


def _check_map(where: str, ds: h5py.Dataset | None, hw: tuple[int, int] | None, channels: tuple[int, ...], limits: Limits, out: _Collector) -> None:
    if ds is None:
        return
    shapes_ok = (ds.ndim == 2 and 1 in channels) or (ds.ndim == 3 and ds.shape[2] in channels)
    if not shapes_ok:
        out.error(where, f"has shape {ds.shape}, expected (H, W{', C' if channels != (1,) else ''})")
    elif hw is not None and tuple(ds.shape[:2]) != hw:
        out.error(where, f"is {ds.shape[0]}×{ds.shape[1]}, but the frames are {hw[0]}×{hw[1]}")
    else:
        _check_pixels(where, ds.shape[0], ds.shape[1], limits, out)


def _check_ground_truth(f: h5py.File, limits: Limits, out: _Collector) -> None:
    g = f.get(layout.GROUND_TRUTH)
    if g is None:
        out.warn("/", "no ground truth: accuracy cannot be measured")
        return
    shape = _frame_shape(f)
    hw = shape[1:3] if shape else None
    where = f"/{layout.GROUND_TRUTH}"
    _check_map(f"{where}/normal", _dataset(g, "normal"), hw, (3,), limits, out)
    _check_map(f"{where}/mask", _dataset(g, "mask"), hw, (1,), limits, out)
    _check_map(f"{where}/albedo", _dataset(g, "albedo"), hw, (1, 3), limits, out)
    _check_map(f"{where}/depth", _dataset(g, "depth"), hw, (1,), limits, out)
    mats = g.get(layout.MATERIALS)
    for key in mats or ():
        _check_map(f"{where}/{layout.MATERIALS}/{key}", _dataset(mats, key), hw, (1, 3), limits, out)


def _check_results(f: h5py.File, limits: Limits, out: _Collector) -> None:
    shape = _frame_shape(f)
    hw = shape[1:3] if shape else None
    for name, g in f.get(layout.RESULTS, {}).items():
        where = f"/{layout.RESULTS}/{name}"
        normal = _dataset(g, "normal")
        if normal is None:
            out.error(where, "dataset 'normal' is missing")
        else:
            _check_map(f"{where}/normal", normal, hw, (3,), limits, out)
        attrs = {key: attr(g, key) for key in (*layout.RESULT_ATTRS, "data_rate")}
        for key in ("solver", "options"):
            if attrs[key] is None:
                out.warn(where, f"attribute {key!r} is missing")
        if attrs["options"] is not None:
            try:
                options = json.loads(attrs["options"]) if isinstance(attrs["options"], str) else None
            except (ValueError, RecursionError):
                options = None
            if not isinstance(options, dict):
                out.error(where, "attribute 'options' is not a JSON object")
        for key in ("seconds", "data_rate"):
            if attrs[key] is not None and not _is_number(attrs[key]):
                out.error(where, f"attribute {key!r} must be a number, got {attrs[key]!r}")


def _check_ratio(f: h5py.File, out: _Collector) -> None:
    shape = _frame_shape(f)
    g = f.get(layout.EVENTS)
    if shape is None or g is None:
        return
    w, h = attr(g, "width"), attr(g, "height")
    if not _is_int(w) or not _is_int(h) or w <= 0 or h <= 0:
        return
    rx, ry = shape[2] / w, shape[1] / h
    if not 0.99 <= rx <= 16 or abs(rx - ry) > 0.02 * rx:
        out.warn("/", f"unusual frame/event resolution ratio {rx:.2f}×{ry:.2f} (expected equal, between 1 and 16)")


def structure_findings(f: h5py.File, limits: Limits | None = None) -> list[Finding]:
    """Findings from metadata, shapes and storage alone (cheap: no data scan). A file whose storage
    is unsound (see ``_check_storage``) gets no further checks: they would read what it declares."""
    limits = limits or Limits.from_env()
    out = _Collector()
    _check_root(f, out)
    if out.failed:
        return list(out)
    _check_storage(f, os.path.getsize(f.filename), limits, out)
    if out.failed:
        return list(out)
    checks = (
        (layout.FRAMES, lambda: _check_frames(f, limits, out)),
        (layout.EVENTS, lambda: _check_events(f, limits, out)),
        (layout.TRIGGERS, lambda: _check_triggers(f, out)),
        (layout.LIGHTS, lambda: _check_lights(f, out)),
    )
    for name, check in checks:
        if name in f:
            check()
    frames = f.get(layout.FRAMES)
    instant = isinstance(frames, h5py.Group) and "light_direction" in frames
    if layout.LIGHTS not in f and not instant:
        out.warn("/", "no light model: solvers cannot use this capture without one")
    _check_calibration(f, out)
    _check_ground_truth(f, limits, out)
    _check_results(f, limits, out)
    _check_ratio(f, out)
    return list(out)


# content -------------------------------------------------------------------------------------------

def _blocks(shape: tuple[int, ...], itemsize: int, budget: int = SCAN_BYTES) -> Iterator[tuple[slice, ...]]:
    """Index tuples that cover an array of ``shape`` in blocks of at most ``budget`` bytes (or one
    innermost row), whole trailing axes first."""
    if not shape or _size(shape) * itemsize <= budget:
        yield tuple(slice(None) for _ in shape)
        return
    inner = _size(shape[1:]) * itemsize
    if inner <= budget:
        step = max(1, budget // max(1, inner))
        for start in range(0, shape[0], step):
            yield (slice(start, min(start + step, shape[0])),) + tuple(slice(None) for _ in shape[1:])
        return
    for i in range(shape[0]):
        for rest in _blocks(shape[1:], itemsize, budget):
            yield (slice(i, i + 1), *rest)


class _Scan:
    """Reads datasets block by block and reports the share of all their bytes read so far."""

    def __init__(self, total_bytes: int, progress: Progress | None) -> None:
        self.total = max(1, total_bytes)
        self.done = 0
        self.progress = progress

    def advance(self, nbytes: int, message: str) -> None:
        self.done += nbytes
        if self.progress is not None:
            self.progress(min(1.0, self.done / self.total), message)

    def read(self, ds: h5py.Dataset, label: str) -> Iterator[tuple[tuple[slice, ...], np.ndarray]]:
        for index in _blocks(ds.shape, ds.dtype.itemsize):
            block = ds[index]
            self.advance(block.nbytes, label)
            yield index, block


def _scan_events(g: h5py.Group, scan: _Scan, out: _Collector) -> None:
    where = f"/{layout.EVENTS}"
    width, height = attr(g, "width"), attr(g, "height")
    n = g["t"].shape[0]
    stored = g["ms_to_idx"]
    builder = MsIndexBuilder()
    checked = 0
    index_ok = True
    previous = None
    for start in range(0, n, SCAN_CHUNK):
        stop = min(start + SCAN_CHUNK, n)
        t = g["t"][start:stop]
        steps = np.flatnonzero(np.diff(t) < 0)
        if steps.size or (previous is not None and t[0] < previous):
            at = start + int(steps[0]) + 1 if steps.size else start
            out.error(f"{where}/t", f"events are not sorted by time (event {at} goes back)")
            return
        if not (_check_time(f"{where}/t", int(t[0]), out) and _check_time(f"{where}/t", int(t[-1]), out)):
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
        # the index entries this block made final, against the stored ones (the index is never whole)
        entries = builder.take()
        index_ok = index_ok and np.array_equal(stored[checked : checked + len(entries)], entries)
        checked += len(entries)
        scan.advance((stop - start) * 11, "events")
    rest = builder.finish()
    index_ok = index_ok and checked + len(rest) == stored.shape[0] and np.array_equal(stored[checked:], rest)
    if attr(g, "ms_origin_us") != builder.origin_us or not index_ok:
        out.error(f"{where}/ms_to_idx", "does not match the event times (rebuild the index)")


def _scan_frames(g: h5py.Group, scan: _Scan, out: _Collector) -> None:
    ds = g["data"]
    saturation = float(attr(g, "saturation"))
    saturated = 0
    for index, block in scan.read(ds, "frames"):
        if ds.dtype.kind == "f" and not np.all(np.isfinite(block)):
            finite = np.isfinite(block.reshape(block.shape[0], -1)).all(axis=1)
            k = (index[0].start or 0) + int(np.flatnonzero(~finite)[0])
            out.error(f"/{layout.FRAMES}/data", f"frame {k} holds NaN or infinite values")
            return
        saturated += int(np.count_nonzero(block >= saturation))
    share = saturated / max(1, ds.size)
    if share > SATURATED_SHARE_WARNING:
        out.warn(f"/{layout.FRAMES}/data", f"{100 * share:.1f} % of the pixel values are saturated")


def _scan_lights(g: h5py.Group, out: _Collector) -> None:
    if attr(g, "model") != "sampled" or "directions" not in g or "times_us" not in g:
        return
    times = g["times_us"][()]
    if times.size and not all(_check_time(f"/{layout.LIGHTS}/times_us", int(v), out) for v in (times.min(), times.max())):
        return
    if np.any(np.diff(times) <= 0):
        out.error(f"/{layout.LIGHTS}/times_us", "sample times are not strictly increasing")
    period = attr(g, "period_us")
    if attr(g, "periodic") and _is_number(period) and times.size and times[-1] - times[0] >= period:
        out.error(f"/{layout.LIGHTS}/times_us", f"samples span {int(times[-1] - times[0])} µs, not less than period_us {period}")
    norms = np.linalg.norm(g["directions"][()], axis=-1)
    worst = float(np.max(np.abs(norms - 1.0))) if norms.size else 0.0
    if worst > UNIT_TOLERANCE:
        out.warn(f"/{layout.LIGHTS}/directions", f"directions are not unit vectors (off by up to {worst:.3g})")


def _scan_triggers(g: h5py.Group, scan: _Scan, out: _Collector) -> None:
    for _, block in scan.read(g["t"], "triggers"):
        if block.size and not all(_check_time(f"/{layout.TRIGGERS}/t", int(v), out) for v in (block.min(), block.max())):
            return
    for c in ("channel", "value"):
        for _ in scan.read(g[c], "triggers"):
            pass


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


def _remaining(f: h5py.File) -> list[tuple[str, h5py.Dataset]]:
    """Every dataset a reader may read that the scans above do not: frame metadata, the light and
    calibration tables, the ground-truth maps and every map of every stored result."""
    found = []
    for name in (layout.FRAMES, layout.LIGHTS, layout.CALIBRATION, layout.GROUND_TRUTH, layout.RESULTS):
        group = f.get(name)
        if group is None:
            continue
        for key, obj in group.items():
            if isinstance(obj, h5py.Dataset) and not (name == layout.FRAMES and key == "data"):
                found.append((f"/{name}/{key}", obj))
            elif isinstance(obj, h5py.Group) and (name == layout.RESULTS or key == layout.MATERIALS):
                found += [(f"/{name}/{key}/{k}", ds) for k, ds in obj.items() if isinstance(ds, h5py.Dataset)]
    return found


def content_findings(f: h5py.File, progress: Progress | None = None) -> list[Finding]:
    """Findings from reading every dataset in bounded memory (assumes the structure is sound);
    ``progress`` hears the share of the bytes read."""
    out = _Collector()
    events, frames, triggers = f.get(layout.EVENTS), f.get(layout.FRAMES), f.get(layout.TRIGGERS)
    rest = _remaining(f)
    total = sum(ds.size * ds.dtype.itemsize for _, ds in rest)
    total += events["t"].shape[0] * 11 if events is not None else 0
    total += frames["data"].size * frames["data"].dtype.itemsize if frames is not None else 0
    total += triggers["t"].size * 10 if triggers is not None else 0
    scan = _Scan(total, progress)
    if events is not None:
        _scan_events(events, scan, out)
    if frames is not None:
        _scan_frames(frames, scan, out)
    if triggers is not None:
        _scan_triggers(triggers, scan, out)
    if layout.LIGHTS in f:
        _scan_lights(f[layout.LIGHTS], out)
    for where, ds in rest:
        for _ in scan.read(ds, where):
            pass
    gt = f.get(layout.GROUND_TRUTH)
    if gt is not None and "normal" in gt and gt["normal"].ndim == 3:
        _scan_normals(f"/{layout.GROUND_TRUTH}", gt, out)
    if progress is not None:
        progress(1.0, "done")
    return list(out)


def inspect(
    f: h5py.File, path: str | os.PathLike[str], *, content: bool, limits: Limits | None = None, progress: Progress | None = None
) -> list[Finding]:
    """The checks the reader and the validator share: structure, then (``content``, and only when the
    structure holds no error) the data. A fatal finding, or anything HDF5 cannot read, raises the
    FormatError that names ``path``."""
    with hdf5_errors(path):
        findings = structure_findings(f, limits)
        fatal = [x for x in findings if x.fatal]
        if fatal:
            raise FormatError(path, fatal[0].text)
        if content and not any(x.level == "error" for x in findings):
            findings += content_findings(f, progress)
    return findings


def check(
    path: Path, *, content: bool, limits: Limits | None = None, progress: Progress | None = None, isolate_check: bool | None = None
) -> list[Finding]:
    """``inspect`` on the file at ``path``, in a child process when ``isolate_check`` (default
    ``psfmt.isolate.enabled()``) says so."""
    if isolate.wanted(isolate_check):
        return isolate.inspect(path, content=content, limits=limits, progress=progress)
    with open_hdf5(path) as f:
        return inspect(f, path, content=content, limits=limits, progress=progress)


def validate(
    path: str | os.PathLike[str],
    *,
    quick: bool = False,
    limits: Limits | None = None,
    progress: Progress | None = None,
    isolate_check: bool | None = None,
) -> ValidationReport:
    """Check a file against the spec: its structure, then (unless ``quick``) every byte of data in
    bounded memory, telling ``progress`` how far the scan is. ``isolate_check`` (default
    ``psfmt.isolate.enabled()``) runs the checks in a child process (see ``psfmt.isolate``). Raises
    FormatError only when the file cannot be read as HDF5 at all, is damaged, or is not a hybrid
    capture of a readable major version."""
    path = Path(path)
    findings = check(path, content=not quick, limits=limits, progress=progress, isolate_check=isolate_check)
    report = ValidationReport(path)
    for finding in findings:
        (report.errors if finding.level == "error" else report.warnings).append(finding)
    return report
