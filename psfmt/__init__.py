"""psfmt — the hybrid-capture format: data model, HDF5 reader and writer, validator.

Depends on numpy and h5py only (numba and isal speed it up where installed). The normative
description is ``spec/hybrid-capture.md``. Foreign event files (Prophesee RAW, Metavision DAT and HDF5,
DSEC-style HDF5, tonic arrays) are read and written by ``psfmt.eventfiles``.

    capture = psfmt.read("scene.h5")           # lazy: frames by index, events by window
    window = capture.events.window(0, 1000)    # the first millisecond, read through the index
    psfmt.write(capture, "copy.h5")            # atomic
    report = psfmt.validate("scene.h5")        # errors and warnings
"""

from __future__ import annotations

__version__ = "0.1.0"

from psfmt._validate.findings import Finding
from psfmt.atomic import atomic_path
from psfmt.camera import CAMERA_MODELS
from psfmt.datarate import DataRate, data_rate, target_size
from psfmt.errors import FormatError
from psfmt.events import EventArray, Events, Triggers
from psfmt.limits import Limits
from psfmt.model import (
    REFRACTORY_RULES,
    Calibration,
    Capture,
    Frames,
    FrameStack,
    GroundTruth,
    LightSpec,
    Result,
    scale_affine,
)
from psfmt.reader import load, read
from psfmt.results import write_result
from psfmt.validate import ValidationReport, validate
from psfmt.version import FORMAT_NAME, FORMAT_VERSION_STR
from psfmt.writer import CaptureWriter, write

__all__ = [
    "CAMERA_MODELS",
    "FORMAT_NAME",
    "FORMAT_VERSION_STR",
    "REFRACTORY_RULES",
    "Calibration",
    "Capture",
    "CaptureWriter",
    "DataRate",
    "EventArray",
    "Events",
    "Finding",
    "FormatError",
    "FrameStack",
    "Frames",
    "GroundTruth",
    "LightSpec",
    "Limits",
    "Result",
    "Triggers",
    "ValidationReport",
    "atomic_path",
    "data_rate",
    "load",
    "read",
    "scale_affine",
    "target_size",
    "validate",
    "write",
    "write_result",
]
