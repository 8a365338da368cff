"""Reading hybrid captures: lazily (frames by index, events by window or chunk) or wholly into memory.

The reader runs the validator's own checks (``psfmt._validate.checks.inspect``) before it reads anything, so
the two agree on every file: the structure always, the data too with ``verify=True``. Sizes are held
against what the file stores and against ``psfmt.Limits`` first, so a file cannot make the reader
allocate more than it holds; every error HDF5 raises becomes a one-line FormatError.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from psfmt import layout
from psfmt.attributes import attrs
from psfmt.camera import PERSPECTIVE
from psfmt.describe import names
from psfmt.errors import FormatError
from psfmt.events import Events, H5EventStore, H5Triggers
from psfmt.files import hdf5_errors, open_hdf5, require_open
from psfmt.limits import Limits
from psfmt.model import (
    Calibration,
    Capture,
    Frames,
    FrameStack,
    GroundTruth,
    LightSpec,
    Result,
)
from psfmt.validate import check


class StoredMaps(Mapping[str, np.ndarray]):
    """The maps of a stored result, each read from the file when it is asked for (sizes were checked
    when the capture was opened)."""

    def __init__(self, group: h5py.Group) -> None:
        self._group = group
        self._path = group.file.filename
        self._names = [k for k, ds in group.items() if isinstance(ds, h5py.Dataset)]

    def __getitem__(self, name: str) -> np.ndarray:
        if name not in self._names:
            raise KeyError(name)
        require_open(self._group, self._path)
        with hdf5_errors(self._path):
            return self._group[name][()]

    def __iter__(self) -> Iterator[str]:
        return iter(self._names)

    def __len__(self) -> int:
        return len(self._names)

    def __repr__(self) -> str:
        return f"StoredMaps({names(self._names)} on disk)"


def _read_lights(group: h5py.Group) -> LightSpec:
    params = attrs(group)
    model = params.pop("model")
    for key, ds in group.items():
        params[key] = np.asarray(ds[()])
    return LightSpec(str(model), params)


def _read_calibration(group: h5py.Group | None) -> Calibration:
    """``/calibration`` as checked by the validator; ``intrinsics`` (3, 3) only of a perspective camera
    (a file before format 1.2 has none: its camera is orthographic)."""
    if group is None:
        return Calibration()
    kwargs: dict[str, Any] = attrs(group, layout.CALIBRATION_ATTRS)
    keys = ["event_to_frame", "view_direction"]
    if kwargs.get("camera_model") == PERSPECTIVE:
        keys.append("intrinsics")
    for key in keys:
        if key in group:
            kwargs[key] = group[key][()]
    name = attrs(group, (layout.SENSOR_MODEL_NAME,))
    if name:
        kwargs["sensor_model"] = {"name": str(name[layout.SENSOR_MODEL_NAME]),
                                  **{k: float(v) for k, v in attrs(group, layout.SENSOR_MODEL_FIGURES).items()}}
    return Calibration(**kwargs)


def _read_ground_truth(group: h5py.Group) -> GroundTruth:
    maps = {k: group[k][()] for k in layout.GT_MAPS if k in group}
    if "mask" in maps:
        maps["mask"] = maps["mask"].astype(bool)
    mats = group.get(layout.MATERIALS)
    materials = {k: ds[()] for k, ds in mats.items()} if mats is not None else {}
    return GroundTruth(**maps, materials=materials)


def _read_result(name: str, group: h5py.Group) -> Result:
    values = attrs(group, (*layout.RESULT_ATTRS, "data_rate"))
    return Result(
        name=name,
        maps=StoredMaps(group),
        solver=str(values.get("solver", name)),
        options=json.loads(values.get("options", "{}")),
        seconds=float(values.get("seconds", 0.0)),
        version=str(values.get("version", "")),
        created=str(values.get("created", "")),
        data_rate=float(values["data_rate"]) if "data_rate" in values else None,
    )


def _capture(fh: h5py.File, path: Path) -> Capture:
    root = attrs(fh, layout.ROOT_ATTRS)
    frames = None
    if layout.FRAMES in fh:
        g = fh[layout.FRAMES]
        frames = Frames(
            FrameStack(g["data"]),
            **{k: g[k][()] for k in layout.FRAME_WINDOW + layout.FRAME_INSTANT if k in g},
            **attrs(g, layout.FRAME_ATTRS),
        )
    events = None
    if layout.EVENTS in fh:
        g = fh[layout.EVENTS]
        events = Events(int(g.attrs["width"]), int(g.attrs["height"]), H5EventStore(g))
    results = {}
    if layout.RESULTS in fh:
        results = {name: _read_result(name, g) for name, g in fh[layout.RESULTS].items()}
    return Capture(
        frames=frames,
        events=events,
        triggers=H5Triggers(fh[layout.TRIGGERS]) if layout.TRIGGERS in fh else None,
        lights=_read_lights(fh[layout.LIGHTS]) if layout.LIGHTS in fh else None,
        calibration=_read_calibration(fh.get(layout.CALIBRATION)),
        ground_truth=_read_ground_truth(fh[layout.GROUND_TRUTH]) if layout.GROUND_TRUTH in fh else None,
        results=results,
        description=str(root.get("description", "")),
        creator=str(root.get("creator", "")),
        creator_version=str(root.get("creator_version", "")),
        created=str(root.get("created", "")),
        format_version=str(root.get("format_version", "")),
        path=path,
        _handle=fh,
    )


def read(
    path: str | os.PathLike[str], *, verify: bool = False, limits: Limits | None = None, isolate_check: bool | None = None
) -> Capture:
    """Open a capture lazily. Frames are read by index, events by time window or in chunks, stored
    results map by map and triggers when first used; metadata, lights, calibration and ground truth
    are read now.

    Structural faults (not HDF5, missing or misshapen datasets, sizes beyond what the file holds or
    beyond ``limits`` (default ``Limits.from_env()``), a newer major version) raise FormatError at
    once. ``verify=True`` also reads all the data in bounded memory (sorted events, polarity and
    coordinate ranges, finite frames, every map readable) and raises on the first fault, exactly as
    ``psfmt.validate`` reports it. A damaged file read later raises FormatError too.
    ``isolate_check`` (default ``psfmt.isolate.enabled()``) runs those checks in a child process, so
    a file that would hang or crash HDF5 is a FormatError instead. Close the capture (or use it as a
    context manager) to release the file.
    """
    path = Path(path)
    problems = [f for f in check(path, content=verify, limits=limits, isolate_check=isolate_check) if f.level == "error"]
    if problems:
        raise FormatError(path, problems[0].text)
    fh = open_hdf5(path)
    try:
        with hdf5_errors(path):
            return _capture(fh, path)
    except BaseException:
        fh.close()
        raise


def load(
    path: str | os.PathLike[str], *, verify: bool = True, limits: Limits | None = None, isolate_check: bool | None = None
) -> Capture:
    """Read a whole capture into memory (frames, events, triggers, results) and close the file."""
    capture = read(path, verify=verify, limits=limits, isolate_check=isolate_check)
    try:
        if capture.frames is not None:
            capture.frames.data = np.asarray(capture.frames.data)
        if capture.events is not None:
            capture.events.data = capture.events.read()
        if capture.triggers is not None:
            capture.triggers = capture.triggers.read()
        for result in capture.results.values():
            result.maps = dict(result.maps)
    finally:
        capture.close()
    return capture
