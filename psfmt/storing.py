"""Storing parts of a capture in an open HDF5 file: compression options, chunk shapes, light
parameters, the calibration and solver results (used by ``psfmt.writer`` and ``psfmt.results``)."""

from __future__ import annotations

import json
from typing import Any

import h5py
import numpy as np

from psfmt import layout
from psfmt.camera import PERSPECTIVE
from psfmt.model import Calibration, Result

_FRAME_CHUNK_BYTES = 1 << 20


def compression_options(level: int) -> dict[str, Any]:
    """h5py dataset options for deflate at ``level`` after shuffle (none for level 0)."""
    # deflate and shuffle are built into every HDF5 library, so any reader in any language opens the file
    return {"compression": "gzip", "compression_opts": level, "shuffle": True} if level > 0 else {}


def row_chunks(shape: tuple[int, ...], itemsize: int, lead: tuple[int, ...] = ()) -> tuple[int, ...]:
    """Chunk shape of whole rows of ``shape`` (rows first), about ``_FRAME_CHUNK_BYTES`` each, after
    the ``lead`` chunk sizes of leading axes (a frame stack's 1)."""
    row_bytes = int(np.prod(shape[1:], dtype=np.int64)) * itemsize
    return (*lead, max(1, min(shape[0], _FRAME_CHUNK_BYTES // max(1, row_bytes))), *shape[1:])


def put_params(group: h5py.Group, params: dict[str, Any]) -> None:
    """A light model's parameters: scalars as attributes of ``group``, arrays as its datasets."""
    for key, value in params.items():
        if isinstance(value, (str, bool, int, float, np.integer, np.floating, np.bool_)):
            group.attrs[key] = value
        else:
            group.create_dataset(key, data=np.asarray(value))


def put_calibration(root: h5py.Group, calibration: Calibration) -> None:
    """``/calibration`` (spec §9): the camera model, with ``intrinsics`` float64 (3, 3) for a
    perspective camera, the view direction (3,), the event→frame affine (2, 3) and the sensor's
    constants. The caller has checked that the camera model and its intrinsics go together."""
    group = root.require_group(layout.CALIBRATION)
    group.attrs["camera_model"] = calibration.camera_model
    if calibration.camera_model == PERSPECTIVE and calibration.intrinsics is not None:
        group.create_dataset("intrinsics", data=np.asarray(calibration.intrinsics, np.float64))
    group.create_dataset("view_direction", data=np.asarray(calibration.view_direction, np.float64))
    if calibration.event_to_frame is not None:
        group.create_dataset("event_to_frame", data=np.asarray(calibration.event_to_frame, np.float64))
    for key in ("contrast_pos", "contrast_neg", "refractory_us"):
        value = getattr(calibration, key)
        if value is not None:
            group.attrs[key] = float(value)
    if calibration.refractory_rule is not None:
        group.attrs["refractory_rule"] = str(calibration.refractory_rule)
    if calibration.sensor_model is not None:
        group.attrs[layout.SENSOR_MODEL_NAME] = str(calibration.sensor_model.get("name", ""))
        for key in layout.SENSOR_MODEL_FIGURES:
            if calibration.sensor_model.get(key) is not None:
                group.attrs[key] = float(calibration.sensor_model[key])


def put_result(root: h5py.Group, result: Result, compress: dict[str, Any] | None = None) -> None:
    """Store one result under ``/results/<name>``, replacing a result of the same name."""
    results = root.require_group(layout.RESULTS)
    if result.name in results:
        del results[result.name]
    group = results.create_group(result.name)
    for key, value in result.maps.items():
        arr = np.asarray(value)
        group.create_dataset(key, data=arr.astype(np.uint8) if arr.dtype == bool else arr, **(compress or {}))
    group.attrs["solver"] = result.solver
    group.attrs["options"] = json.dumps(result.options, sort_keys=True, default=str)
    group.attrs["seconds"] = float(result.seconds)
    group.attrs["version"] = result.version
    group.attrs["created"] = result.created
    if result.data_rate is not None:
        group.attrs["data_rate"] = float(result.data_rate)
