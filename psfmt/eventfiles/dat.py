"""Metavision DAT files of CD events: decoding in bounded memory and writing, bit-exactly.

A DAT file is ``% key value`` header lines (the RAW header's syntax, ``psfmt.eventfiles.rawheader``), two bytes
(the event type: 12 for EventCD, or 0 for the older Event2d; the event size: 8), then 8-byte
little-endian records: a uint32 timestamp in µs, and a uint32 holding x in bits 0–13, y in bits
14–27 and the polarity in bits 28–31 (1: brighter → p = +1, 0: darker → p = −1). That is the
``RawEvent`` of OpenEB's ``Event2d`` (``sdk/modules/base/cpp/include/metavision/sdk/base/events/
event2d.h``), read by ``sdk/modules/stream/cpp/src/dat_event_file_reader.cpp`` and by Prophesee's
Python ``load_td_data`` (``src/io/dat_events_tools.py`` of prophesee-automotive-dataset-toolbox).

The geometry comes from ``% Width`` / ``% Height`` (or anything ``resolve_geometry`` reads). Damaged
input gets the answers the RAW decoders give: nothing is guessed; records outside the geometry are
dropped and records whose polarity field is neither 0 nor 1 skipped, both counted in
``DecodeStats``; a last partial record (a truncated file) is ignored and reported with its byte
offset; a header that is not a DAT header, or an event type other than CD, is a one-line FormatError.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from psfmt.atomic import atomic_path
from psfmt.errors import FormatError
from psfmt.eventfiles.rawheader import DecodeStats, RawHeader, iter_words, missing_geometry, read_header
from psfmt.events import EventArray

EVENT_2D, EVENT_CD, EVENT_EXT_TRIGGER = 0, 12, 14
EVENT_SIZE = 8
RECORD = np.dtype([("t", "<u4"), ("w", "<u4")])
MAX_COORD = (1 << 14) - 1
MAX_TIME_US = (1 << 32) - 1
DEFAULT_CHUNK_RECORDS = 1 << 20


def decode(records: np.ndarray | bytes, width: int = MAX_COORD + 1, height: int = MAX_COORD + 1, stats: DecodeStats | None = None) -> EventArray:
    """The CD events of DAT records (bytes after the type/size pair, or a ``RECORD`` array) with x, y
    below ``width`` × ``height``; skipped and dropped records are counted in ``stats``."""
    if isinstance(records, (bytes, bytearray, memoryview)):
        records = np.frombuffer(records, dtype=RECORD, count=len(records) // EVENT_SIZE)
    stats = stats if stats is not None else DecodeStats(unit="record")
    w = records["w"].astype(np.int64)
    x, y, pol = w & MAX_COORD, (w >> 14) & MAX_COORD, w >> 28
    polar = pol <= 1
    inside = (x < width) & (y < height)
    keep = polar & inside
    stats.bad_polarity += int(np.count_nonzero(~polar))
    stats.outside += int(np.count_nonzero(polar & ~inside))
    events = EventArray(x[keep], y[keep], records["t"][keep].astype(np.int64), np.where(pol[keep] == 1, 1, -1))
    stats.events += len(events)
    return events


def encode(events: EventArray) -> bytes:
    """The records of ``events`` (no header); ``decode(encode(e))`` gives ``e`` back exactly. Times must
    lie in [0, 2^32) µs and x, y be at most 16383 (the format's 14 bits)."""
    if len(events) == 0:
        return b""
    if int(events.t.min()) < 0 or int(events.t.max()) > MAX_TIME_US:
        raise ValueError(f"DAT times are uint32 µs: every time must lie in [0, {MAX_TIME_US}]")
    if int(events.x.max()) > MAX_COORD or int(events.y.max()) > MAX_COORD:
        raise ValueError(f"DAT coordinates are 14-bit: x and y must be at most {MAX_COORD}")
    out = np.empty(len(events), RECORD)
    out["t"] = events.t
    out["w"] = events.x.astype(np.uint32) | (events.y.astype(np.uint32) << 14) | ((events.p > 0).astype(np.uint32) << 28)
    return out.tobytes()


def format_header(width: int, height: int, extra: dict[str, str] | None = None) -> bytes:
    """The header Metavision writes for CD events (``% Width``/``% Height``, as its reader takes the
    geometry), extra lines, and the event type and size bytes."""
    lines = ["% Data file containing CD events", "% Version 2", f"% Width {width}", f"% Height {height}"]
    lines += [f"% {key} {value}" for key, value in (extra or {}).items()]
    return ("\n".join(lines) + "\n").encode("ascii") + bytes([EVENT_CD, EVENT_SIZE])


def _event_type(path: Path, header: RawHeader) -> tuple[int, int] | None:
    """The type and size bytes after the header (None when the file ends first); FormatError for a
    file that is not a DAT file of CD events."""
    with open(path, "rb") as fh:
        fh.seek(header.data_offset)
        pair = fh.read(2)
    if not header.lines:
        raise FormatError(path, "no '% ' header lines: not a Metavision DAT file")
    if len(pair) < 2:
        return None
    kind, size = pair[0], pair[1]
    if kind == EVENT_EXT_TRIGGER:
        raise FormatError(path, "DAT file holds external-trigger events (type 14), not CD events")
    if kind not in (EVENT_CD, EVENT_2D):
        raise FormatError(path, f"DAT event type {kind} is not CD (12) or Event2d (0): not a DAT file of CD events")
    if size != EVENT_SIZE:
        raise FormatError(path, f"DAT events are {size} bytes, not {EVENT_SIZE}")
    return kind, size


class DatFile:
    """A DAT file of CD events, decoded in bounded memory (``chunks``) or at once (``read``); ``stats``
    sums up the last pass. The sensor size is the header's unless ``geometry`` gives it."""

    def __init__(
        self, path: str | os.PathLike[str], *, chunk_records: int = DEFAULT_CHUNK_RECORDS, geometry: tuple[int, int] | None = None
    ) -> None:
        self.path = Path(path)
        self.header = read_header(self.path, label="DAT", geometry=geometry)
        pair = _event_type(self.path, self.header)
        if self.header.width is None or self.header.height is None:
            raise FormatError(self.path, missing_geometry(self.header))
        self.width, self.height = int(self.header.width), int(self.header.height)
        self.event_type = pair[0] if pair else None
        self._pair_bytes = 0 if pair is None else 2
        self.chunk_records = int(chunk_records)
        self.stats = DecodeStats(unit="record")

    @property
    def data_offset(self) -> int:
        """The first record's byte offset (after the header and the type/size pair)."""
        return self.header.data_offset + self._pair_bytes

    def chunks(self) -> Iterator[EventArray]:
        """The events block by block, in file order."""
        self.stats = DecodeStats(unit="record")
        tail = self.path.stat().st_size - self.header.data_offset
        if self._pair_bytes == 0 and tail > 0:  # one byte of the type/size pair: a cut-off file
            self.stats.trailing_bytes, self.stats.trailing_offset = tail, self.header.data_offset
            return
        body = RawHeader(self.header.fields, data_offset=self.data_offset)
        for _, records in iter_words(self.path, body, RECORD, self.chunk_records, self.stats):
            yield decode(records, self.width, self.height, self.stats)

    def read(self) -> EventArray:
        return EventArray.concatenate(list(self.chunks()))


def write_dat(
    path: str | os.PathLike[str], chunks: Iterable[EventArray], width: int, height: int, *, header: dict[str, str] | None = None
) -> Path:
    """Write a DAT file of CD events (header, type/size pair and records) from event blocks, atomically."""
    path = Path(path)
    if not (0 < width <= MAX_COORD + 1 and 0 < height <= MAX_COORD + 1):
        raise FormatError(path, f"DAT holds sensors up to {MAX_COORD + 1}×{MAX_COORD + 1}, not {width}×{height}")
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(format_header(width, height, header))
        for block in chunks:
            fh.write(encode(block))
    return path
