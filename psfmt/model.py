"""The data model of a hybrid capture: plain dataclasses, numpy arrays or lazy on-disk views.

A capture holds frames only (classic photometric stereo), events only (EventPS) or both (DualResPS),
plus the light model, calibration, optional ground truth and stored solver results. Units: time in
int64 microseconds, lengths in millimetres, angles in degrees, pixels as (column u → right, row v ↓).

Every class has a one-line ``repr`` of a few hundred characters at most: sizes, dtypes, counts and
names (cut, printable), never array contents, and no file access (it works on a closed capture).
"""

from __future__ import annotations

import datetime as _dt
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from psfmt.describe import array_text, cut, names, path_text, quoted, value_text
from psfmt.events import Events, H5Triggers, Triggers
from psfmt.files import hdf5_errors

FRAME_DTYPES = (np.dtype(np.uint8), np.dtype(np.uint16), np.dtype(np.float32))
REFRACTORY_RULES = ("reset-at-end", "rate-limited")
"""Values of ``Calibration.refractory_rule`` (spec §9): the reference resets to the level at the end of
the refractory period, or moves one threshold per event while a persisting change fires every period."""
COLOR_ORDERS = {"RGB": 3, "L": 1}


def utc_now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat()


def _stack_text(data: Any) -> str:
    """``K × H×W×C dtype`` of a frame stack (``dtype[shape]`` when it is not 4-D: a repr never raises)."""
    shape = tuple(int(d) for d in data.shape)
    if len(shape) != 4:
        return array_text(data)
    k, h, w, c = shape
    return f"{k} × {h}×{w}×{c} {np.dtype(data.dtype)}"


class FrameStack:
    """A lazy (K, H, W, C) view of the frames dataset: indexing reads only what is asked for."""

    def __init__(self, dataset: Any) -> None:
        self._ds = dataset

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(self._ds.shape)

    @property
    def dtype(self) -> np.dtype[Any]:
        return self._ds.dtype

    @property
    def ndim(self) -> int:
        return len(self.shape)

    def __len__(self) -> int:
        return int(self._ds.shape[0])

    def __getitem__(self, index: Any) -> np.ndarray:
        with hdf5_errors(self._ds.file.filename):
            return np.asarray(self._ds[index])

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        arr = self[()]
        return arr if dtype is None else arr.astype(dtype)

    def __repr__(self) -> str:
        return f"FrameStack({array_text(self)} on disk)"


@dataclass
class Frames:
    """K frames of H×W pixels with C channels, linear in irradiance.

    Long-exposure captures give each frame an exposure window [t_start_us, t_end_us); classic captures
    (DiLiGenT) give an instantaneous light direction (unit, camera frame) and RGB intensity per frame.
    ``saturation`` is the pixel value at which the sensor clips, in stored units; ``bit_depth`` the
    significant bits of an integer sensor (e.g. 12 in uint16). ``len(frames)`` is K.
    """

    data: np.ndarray | FrameStack
    t_start_us: np.ndarray | None = None
    t_end_us: np.ndarray | None = None
    light_direction: np.ndarray | None = None
    light_intensity: np.ndarray | None = None
    color_order: str = "RGB"
    bit_depth: int | None = None
    saturation: float | None = None
    black_level: float = 0.0
    response: str = "linear"

    def __post_init__(self) -> None:
        dtype = np.dtype(self.data.dtype)
        if self.bit_depth is None:
            self.bit_depth = 32 if dtype.kind == "f" else dtype.itemsize * 8
        if self.saturation is None:
            self.saturation = 1.0 if dtype.kind == "f" else float(2 ** int(self.bit_depth) - 1)
        for name in ("t_start_us", "t_end_us"):
            value = getattr(self, name)
            if value is not None:
                setattr(self, name, np.asarray(value, dtype=np.int64))
        for name in ("light_direction", "light_intensity"):
            value = getattr(self, name)
            if value is not None:
                setattr(self, name, np.asarray(value, dtype=np.float64))

    def __len__(self) -> int:
        return self.count

    def __repr__(self) -> str:
        timing = "exposure windows" if self.has_windows else "instant lights" if self.has_instant_lights else "untimed"
        where = ", on disk" if isinstance(self.data, FrameStack) else ""
        return f"Frames({_stack_text(self.data)}, {self.bit_depth}-bit, {timing}{where})"

    @property
    def count(self) -> int:
        return int(self.data.shape[0])

    @property
    def height(self) -> int:
        return int(self.data.shape[1])

    @property
    def width(self) -> int:
        return int(self.data.shape[2])

    @property
    def channels(self) -> int:
        return int(self.data.shape[3])

    @property
    def has_windows(self) -> bool:
        return self.t_start_us is not None and self.t_end_us is not None

    @property
    def has_instant_lights(self) -> bool:
        return self.light_direction is not None

    def frame(self, k: int) -> np.ndarray:
        return np.asarray(self.data[k])

    def as_float(self, k: int | slice = slice(None)) -> np.ndarray:
        """Frame(s) as float32 in units of the saturation level (1.0 = clipped), black level removed."""
        raw = np.asarray(self.data[k], dtype=np.float32)
        scale = float(self.saturation) - float(self.black_level)
        return (raw - float(self.black_level)) / scale


@dataclass
class LightSpec:
    """A light model by registry name with its parameters (scalars, strings or arrays).

    The parameters of the built-in models (``ring``, ``sampled``, ``near-ring``) are defined in the
    spec; a plugin's model stores whatever its registry entry needs.
    """

    model: str
    params: dict[str, Any] = field(default_factory=dict)

    def __repr__(self) -> str:
        # scalars as themselves, arrays by dtype and shape; a plugin's model may carry many parameters
        shown = [f"{cut(key)}={value_text(value)}" for key, value in list(self.params.items())[:6]]
        if len(self.params) > 6:
            shown.append(f"+{len(self.params) - 6} more")
        return f"LightSpec({', '.join([quoted(self.model), *shown])})"


@dataclass
class Calibration:
    """How the two cameras and the sensor relate.

    ``event_to_frame`` maps event pixel centres (u_e, v_e, 1) to frame pixel coordinates (u_f, v_f);
    contrast thresholds are in natural-log units; the refractory period in µs, and what a pixel does
    after it, ``refractory_rule`` (one of ``REFRACTORY_RULES``; None, when unknown, means
    ``"reset-at-end"``, spec §9).

    ``camera_model`` is ``"orthographic"`` or ``"perspective"`` (``psfmt.camera.CAMERA_MODELS``, spec
    §9.1); a perspective camera has ``intrinsics``, the float64 (3, 3) pinhole matrix
    K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]] in frame pixels (centre of projection at the origin,
    scene at z < 0; ``psfmt.camera`` states the projection), an orthographic one None.
    ``view_direction`` (3,) is the unit vector from the surface to the camera (for a perspective
    camera, that of the principal point). ``sensor_model`` (spec §9.2, optional): how the sensors of a
    synthetic capture were modelled, ``{"name": str, figure: float …}`` with the figures of
    ``psfmt.layout.SENSOR_MODEL_FIGURES`` it records.
    """

    event_to_frame: np.ndarray | None = None
    contrast_pos: float | None = None
    contrast_neg: float | None = None
    refractory_us: float | None = None
    refractory_rule: str | None = None
    camera_model: str = "orthographic"
    view_direction: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    intrinsics: np.ndarray | None = None
    sensor_model: dict[str, Any] | None = None

    def __post_init__(self) -> None:
        for name in ("event_to_frame", "intrinsics"):
            value = getattr(self, name)
            if value is not None:
                setattr(self, name, np.asarray(value, dtype=np.float64))
        self.view_direction = np.asarray(self.view_direction, dtype=np.float64)

    def __repr__(self) -> str:
        parts = [cut(self.camera_model)]
        if self.intrinsics is not None:
            parts.append("intrinsics")
        if self.contrast_pos is not None or self.contrast_neg is not None:
            parts.append(f"contrast +{value_text(self.contrast_pos)}/−{value_text(self.contrast_neg)}")
        if self.refractory_us is not None:
            parts.append(f"refractory {value_text(self.refractory_us)} µs")
        if self.refractory_rule is not None:
            parts.append(cut(self.refractory_rule))
        if self.event_to_frame is not None:
            parts.append("event→frame affine")
        if self.sensor_model is not None:
            parts.append(f"sensor model {cut(str(self.sensor_model.get('name', '')))}")
        return f"Calibration({', '.join(parts)})"


def scale_affine(event_scale: float) -> np.ndarray:
    """The event→frame affine of an event sensor that samples the frame's view at ``event_scale``
    event pixels per frame pixel with the same field of view (pixel centres at integers)."""
    s = 1.0 / float(event_scale)
    return np.array([[s, 0.0, 0.5 * s - 0.5], [0.0, s, 0.5 * s - 0.5]])


@dataclass
class GroundTruth:
    """Reference maps at frame resolution: unit normals (camera frame, x right, y up, z to camera),
    mask, optional RGB albedo, depth and material maps (``f0``, ``roughness``, ``metallic`` …)."""

    normal: np.ndarray | None = None
    mask: np.ndarray | None = None
    albedo: np.ndarray | None = None
    depth: np.ndarray | None = None
    materials: dict[str, np.ndarray] = field(default_factory=dict)

    def __repr__(self) -> str:
        present = {k: v for k, v in (("normal", self.normal), ("mask", self.mask), ("albedo", self.albedo), ("depth", self.depth)) if v is not None}
        if not present and not self.materials:
            return "GroundTruth(empty)"
        first = next(iter(present.values()), None)
        size = f"{first.shape[0]}×{first.shape[1]}: " if first is not None and np.ndim(first) >= 2 else ""
        materials = f"; materials {names(self.materials)}" if self.materials else ""
        return f"GroundTruth({size}{', '.join(present)}{materials})"


@dataclass
class Result:
    """Maps a solver wrote (``normal`` (H, W, 3) at least) and how they were made; ``data_rate`` is the
    share of 24 RGB frames per period that the solver's inputs amount to (None when unknown). A
    result read from a file reads each map when it is asked for."""

    name: str
    maps: Mapping[str, np.ndarray]
    solver: str
    options: dict[str, Any] = field(default_factory=dict)
    seconds: float = 0.0
    version: str = ""
    created: str = field(default_factory=utc_now)
    data_rate: float | None = None

    def __repr__(self) -> str:
        rate = "" if self.data_rate is None else f", data rate {100 * self.data_rate:.1f} %"
        return (f"Result({quoted(self.name)}, solver {quoted(self.solver)}, maps: {names(self.maps)}, "
                f"{value_text(self.seconds)} s{rate})")


@dataclass
class Capture:
    """One capture: what the cameras recorded, under which lights, and what is known about it.
    ``len(capture.frames)`` is its number of frames, ``len(capture.events)`` of events."""

    frames: Frames | None = None
    events: Events | None = None
    triggers: Triggers | H5Triggers | None = None
    lights: LightSpec | None = None
    calibration: Calibration = field(default_factory=Calibration)
    ground_truth: GroundTruth | None = None
    results: dict[str, Result] = field(default_factory=dict)
    description: str = ""
    creator: str = "psfmt"
    creator_version: str = ""
    created: str = field(default_factory=utc_now)
    format_version: str = ""
    path: Path | None = None
    _handle: Any = field(default=None, repr=False, compare=False)

    def __repr__(self) -> str:
        parts = [self.kind]
        if self.path is not None:
            parts.append(path_text(self.path))
        if self.frames is not None:
            parts.append(f"frames {_stack_text(self.frames.data)}")
        if self.events is not None:
            parts.append(f"{len(self.events)} events {self.events.width}×{self.events.height}")
        if self.triggers is not None:
            parts.append(f"{len(self.triggers)} trigger edges")
        if self.lights is not None:
            parts.append(f"lights {quoted(self.lights.model)}")
        if self.ground_truth is not None:
            parts.append("ground truth")
        if self.results:
            parts.append(f"results: {names(self.results)}")
        if self.format_version:
            parts.append(f"format {cut(self.format_version, 12)}")
        return f"Capture({', '.join(parts)})"

    @property
    def kind(self) -> str:
        """``hybrid``, ``frames`` or ``events``: what the capture holds."""
        if self.frames is not None and self.events is not None:
            return "hybrid"
        return "frames" if self.frames is not None else "events" if self.events is not None else "empty"

    def close(self) -> None:
        """Release the file behind lazy frames and events (a no-op for in-memory captures)."""
        if self._handle is not None:
            self._handle.close()
            self._handle = None

    def __enter__(self) -> Capture:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
