"""How much a file may make the reader allocate: the format's fixed bounds and the configurable limits.

A declared shape is only a claim: an HDF5 file of a few kilobytes can declare a 150 GiB map, 10¹¹
events or a 2³¹ × 2³¹ sensor. The validator, which the reader runs on every file, compares each
declared size with what the file stores (at most ``DEFLATE_MAX_RATIO`` times the stored bytes once
inflated) and with the ``Limits`` below, before anything is read.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, fields

from psfmt.errors import FormatError

DEFLATE_MAX_RATIO = 1032
"""The most that deflate inflates: a 258-byte match costs at least 2 bits (RFC 1951), so ≈ 1032:1."""
FILL_ALLOWANCE = 1 << 20
"""Bytes a dataset may declare beyond its storage limit: small datasets HDF5 fills with its fill value."""
MAX_SENSOR_SIDE = 1 << 16
"""Event coordinates are uint16, so an event sensor is at most 65 536 pixels wide and high."""
MAX_ABS_TIME_US = 1 << 53
"""Times lie within ±2⁵³ µs (±285 years): every one of them converts to float64 exactly."""
SMALL_CHUNK_BYTES = 4096
MAX_SMALL_CHUNKS = 16384
"""A dataset cut into more than ``MAX_SMALL_CHUNKS`` chunks under ``SMALL_CHUNK_BYTES`` is refused: HDF5
keeps about 6.5 KB of bookkeeping for each chunk a read touches, so 10⁶ chunks of a 1×1 frame (3 bytes
each) cost 6.5 GB to read for 3 MB of data. The writer never makes such chunks."""


@dataclass(frozen=True)
class Limits:
    """Sane bounds on what one capture may make a reader allocate; files beyond them are refused.

    ``max_pixels``: pixels of one image (a frame, a map) or of the event sensor (67 M: 8192²).
    ``max_array_bytes``: bytes of an array read whole (one frame, a map, the triggers, the
    millisecond index, a light or calibration table). ``max_chunk_bytes``: bytes of one HDF5 chunk
    (a chunk is inflated whole to read any part of it). Each can be raised through the environment
    variable of the same name in capitals with a ``PSFMT_`` prefix (``PSFMT_MAX_PIXELS`` …).
    """

    max_pixels: int = 1 << 26
    max_array_bytes: int = 1 << 30
    max_chunk_bytes: int = 1 << 26

    @classmethod
    def from_env(cls, environ: Mapping[str, str] | None = None) -> Limits:
        """The defaults, each replaced by its ``PSFMT_…`` environment variable where that is set."""
        environ = os.environ if environ is None else environ
        values = {}
        for f in fields(cls):
            name = f"PSFMT_{f.name.upper()}"
            text = environ.get(name)
            if text is None:
                continue
            try:
                value = int(text)
            except ValueError:
                value = 0
            if value <= 0:
                raise FormatError(name, f"expected a positive integer, got {text!r}")
            values[f.name] = value
        return cls(**values)
