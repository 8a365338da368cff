"""Reading hybrid captures: lazily (frames by index, events by window or chunk) or wholly into memory."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from psfmt import layout
from psfmt.errors import FormatError
from psfmt.files import damaged, open_hdf5
from psfmt.events import Events, H5EventStore, Triggers
from psfmt.model import (
    Calibration,
    Capture,
    FrameStack,
    Frames,
    GroundTruth,
    LightSpec,
    Result,
)
from psfmt.validate import content_findings, structure_findings


def _plain(value: Any) -> Any:
    """HDF5 attribute values as plain Python (str, int, float, bool) or numpy arrays."""
    if isinstance(value, bytes):
        return value.decode()
    if isinstance(value, np.generic):
        return value.item()
    return value


def _read_lights(group: h5py.Group) -> LightSpec:
    params: dict[str, Any] = {k: _plain(v) for k, v in group.attrs.items() if k != "model"}
    for key, ds in group.items():
        params[key] = np.asarray(ds[()])
    return LightSpec(str(_plain(group.attrs["model"])), params)


def _read_calibration(group: h5py.Group | None) -> Calibration:
    if group is None:
        return Calibration()
    attrs = {k: _plain(v) for k, v in group.attrs.items()}
    kwargs: dict[str, Any] = {k: attrs[k] for k in layout.CALIBRATION_ATTRS if k in attrs}
    for key in ("event_to_frame", "view_direction"):
        if key in group:
            kwargs[key] = group[key][()]
    return Calibration(**kwargs)


def _read_ground_truth(group: h5py.Group) -> GroundTruth:
    maps = {k: group[k][()] for k in layout.GT_MAPS if k in group}
    if "mask" in maps:
        maps["mask"] = maps["mask"].astype(bool)
    mats = group.get(layout.MATERIALS)
    materials = {k: ds[()] for k, ds in mats.items()} if mats is not None else {}
    return GroundTruth(**maps, materials=materials)


def _read_result(name: str, group: h5py.Group) -> Result:
    attrs = {k: _plain(v) for k, v in group.attrs.items()}
    return Result(
        name=name,
        maps={k: ds[()] for k, ds in group.items() if isinstance(ds, h5py.Dataset)},
        solver=str(attrs.get("solver", name)),
        options=json.loads(attrs.get("options", "{}")),
        seconds=float(attrs.get("seconds", 0.0)),
        version=str(attrs.get("version", "")),
        created=str(attrs.get("created", "")),
        data_rate=float(attrs["data_rate"]) if "data_rate" in attrs else None,
    )


def read(path: str | os.PathLike[str], *, verify: bool = False) -> Capture:
    """Open a capture lazily. Frames are read by index and events by time window or in chunks;
    only metadata, lights, calibration, ground truth and results are read now.

    Structural faults (not HDF5, missing or misshapen datasets, a newer major version) raise
    FormatError at once. ``verify=True`` also scans contents in bounded memory (sorted events,
    polarity and coordinate ranges, finite frames) and raises on the first fault. Close the capture
    (or use it as a context manager) to release the file.
    """
    path = Path(path)
    fh = open_hdf5(path)
    try:
        problems = [f for f in structure_findings(fh) if f.level == "error"]
        if verify and not problems:
            problems = [f for f in content_findings(fh) if f.level == "error"]
        if problems:
            raise FormatError(path, problems[0].text)
        root = {k: _plain(v) for k, v in fh.attrs.items()}
        frames = None
        if layout.FRAMES in fh:
            g = fh[layout.FRAMES]
            attrs = {k: _plain(v) for k, v in g.attrs.items()}
            frames = Frames(
                FrameStack(g["data"]),
                **{k: g[k][()] for k in layout.FRAME_WINDOW + layout.FRAME_INSTANT if k in g},
                **{k: attrs[k] for k in layout.FRAME_ATTRS if k in attrs},
            )
        events = None
        if layout.EVENTS in fh:
            g = fh[layout.EVENTS]
            events = Events(int(g.attrs["width"]), int(g.attrs["height"]), H5EventStore(g))
        triggers = None
        if layout.TRIGGERS in fh:
            g = fh[layout.TRIGGERS]
            triggers = Triggers(g["t"][()], g["channel"][()], g["value"][()])
        results = {}
        if layout.RESULTS in fh:
            results = {name: _read_result(name, g) for name, g in fh[layout.RESULTS].items()}
        return Capture(
            frames=frames,
            events=events,
            triggers=triggers,
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
    except FormatError:
        fh.close()
        raise
    except OSError as exc:
        fh.close()
        raise damaged(path, exc) from exc
    except (KeyError, ValueError) as exc:
        fh.close()
        raise FormatError(path, f"damaged file ({exc})") from exc


def load(path: str | os.PathLike[str], *, verify: bool = True) -> Capture:
    """Read a whole capture into memory and close the file."""
    capture = read(path, verify=verify)
    try:
        if capture.frames is not None:
            capture.frames.data = np.asarray(capture.frames.data)
        if capture.events is not None:
            capture.events.data = capture.events.read()
    finally:
        capture.close()
    return capture
