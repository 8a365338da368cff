"""The ASCII header of Prophesee RAW files (EVT 2.0 / EVT 3.0) and Metavision DAT files: ``% key value``
lines before the data.

The data begins at the first line that does not start with ``% `` (or right after ``% end``), as the
vendor's readers define it (OpenEB ``GenericHeader::parse_header``); the lines may come in any order.
The sensor geometry is resolved as Metavision resolves it (``resolve_geometry``): ``% geometry WxH``,
the ``width=``/``height=`` fields of ``% format``, the older ``% Width`` / ``% Height`` lines, and then
the Prophesee sensor that ``system_ID``, ``plugin_name``, ``sensor_name`` or ``sensor_generation``
implies (``psfmt.eventfiles.rawsensors``); a geometry given by the caller overrides them all.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

import numpy as np

from psfmt.errors import FormatError
from psfmt.eventfiles.rawsensors import implied_encoding, implied_sensor, shown, unknown_identity
from psfmt.events import Triggers
from psfmt.limits import MAX_SENSOR_SIDE

MAX_HEADER_BYTES = 1 << 20
ENCODINGS = ("EVT3", "EVT2", "EVT21")


@dataclass
class RawHeader:
    """A parsed header: ``fields`` (key → value text; a repeated key keeps its last value), ``lines``
    (every header line as written, in file order, without ``% end``), the resolved geometry and where
    it came from (``geometry_source``, e.g. ``"system_ID 48 (Gen4.1)"``), the encoding and the offset
    of the first data byte."""

    fields: dict[str, str] = field(default_factory=dict)
    width: int | None = None
    height: int | None = None
    encoding: str | None = None
    data_offset: int = 0
    lines: list[str] = field(default_factory=list)
    geometry_source: str | None = None
    label: str = "RAW"


_GEOMETRY = re.compile(r"^\s*(\d{1,12})\s*[xX×]\s*(\d{1,12})\s*$")


def parse_geometry(text: str) -> tuple[int, int] | None:
    """``(width, height)`` of a ``WxH`` text (``1280x720``), None if it is not one."""
    match = _GEOMETRY.match(text)
    return (int(match[1]), int(match[2])) if match else None


def _check_sides(width: int, height: int, path: Path, label: str) -> tuple[int, int]:
    """The geometry, each side within 1…65536 pixels (what a capture's uint16 holds); FormatError otherwise."""
    if not (0 < width <= MAX_SENSOR_SIDE and 0 < height <= MAX_SENSOR_SIDE):
        raise FormatError(path, f"{label} header declares a {width}×{height} sensor; each side must be 1…{MAX_SENSOR_SIDE} pixels")
    return width, height


def _format_options(fields: dict[str, str]) -> dict[str, str]:
    return dict(part.strip().split("=", 1) for part in fields.get("format", "").split(";")[1:] if "=" in part)


def resolve_geometry(
    fields: dict[str, str], path: Path, label: str = "RAW", override: tuple[int, int] | None = None
) -> tuple[int, int, str] | None:
    """``(width, height, source)`` of the sensor, in Metavision's order: ``override`` (the caller's
    ``--geometry``), ``% geometry WxH``, ``% format …;width=W;height=H`` (both present must agree, as
    Metavision requires), ``% Width`` / ``% Height``, then the sensor the Prophesee tables imply
    (``psfmt.eventfiles.rawsensors.implied_sensor``); None when nothing declares or implies one. A declared
    geometry that is unreadable, contradictory or beyond 1…65536 pixels a side is a FormatError."""
    if override is not None:
        width, height = _check_sides(*override, path, label)
        return width, height, f"--geometry {width}x{height}"
    unreadable = f"{label} header has an unreadable sensor geometry"
    declared = None
    if "geometry" in fields:
        geometry = parse_geometry(fields["geometry"])
        if geometry is None:
            raise FormatError(path, f"{unreadable} (% geometry {shown(fields['geometry'])})")
        declared = (*_check_sides(*geometry, path, label), f"geometry {shown(fields['geometry'])}")
    fmt = _format_options(fields)
    if "width" in fmt and "height" in fmt:
        try:
            sides = int(fmt["width"]), int(fmt["height"])
        except ValueError:
            raise FormatError(path, f"{unreadable} (% format {shown(fields['format'])})") from None
        width, height = _check_sides(*sides, path, label)
        if declared is not None and declared[:2] != (width, height):
            raise FormatError(
                path, f"{label} header's % geometry {shown(fields['geometry'])} and % format {shown(fields['format'])} disagree"
            )
        declared = declared or (width, height, f"format {shown(fields['format'])}")
    if declared is not None:
        return declared
    if "Width" in fields and "Height" in fields:
        try:
            sides = int(fields["Width"]), int(fields["Height"])
        except ValueError:
            raise FormatError(path, f"{unreadable} (% Width {shown(fields['Width'])}, % Height {shown(fields['Height'])})") from None
        width, height = _check_sides(*sides, path, label)
        return width, height, f"Width {width}, Height {height}"
    implied = implied_sensor(fields)
    if implied is not None:
        sensor, source = implied
        return sensor.width, sensor.height, source
    return None


def missing_geometry(header: RawHeader) -> str:
    """The one-line reason a header has no geometry: everything that was looked for, and what the
    header names that the sensor tables do not know."""
    looked = (
        f"{header.label} header declares no sensor geometry: no % geometry WxH, no width=/height= in % format, "
        "no % Width/% Height, and no Prophesee sensor known from system_ID, plugin_name, sensor_name or sensor_generation"
    )
    unknown = unknown_identity(header.fields)
    return f"{looked} ({unknown})" if unknown else looked


def _encoding(fields: dict[str, str]) -> str | None:
    fmt = fields.get("format", "").split(";")[0].strip().upper()
    if fmt in ENCODINGS:
        return fmt
    evt = fields.get("evt", "").strip()
    declared = {"3.0": "EVT3", "2.0": "EVT2", "2.1": "EVT21"}.get(evt)
    return declared or implied_encoding(fields)


def parse_header(
    fh: BinaryIO, path: str | os.PathLike[str], *, label: str = "RAW", geometry: tuple[int, int] | None = None
) -> RawHeader:
    """Read the header from the start of ``fh`` and leave ``fh`` at the first data byte; ``geometry``
    overrides whatever the header declares (``label`` names the file kind in messages)."""
    path = Path(path)
    fields: dict[str, str] = {}
    lines: list[str] = []
    offset = 0
    fh.seek(0)
    while True:
        if offset > MAX_HEADER_BYTES:
            raise FormatError(path, f"{label} header longer than {MAX_HEADER_BYTES} bytes (not a {label} file?)")
        start = fh.read(2)
        if start != b"% ":
            break
        line = b"% " + fh.readline(MAX_HEADER_BYTES)
        offset += len(line)
        text = line[2:].decode("ascii", errors="replace").strip()
        parts = text.split(None, 1)
        if parts and parts[0] == "end":
            break
        if parts:
            fields[parts[0]] = parts[1].strip() if len(parts) > 1 else ""
        lines.append(line.decode("ascii", errors="replace").rstrip("\r\n"))
    fh.seek(offset)
    header = RawHeader(fields, encoding=_encoding(fields), data_offset=offset, lines=lines, label=label)
    resolved = resolve_geometry(fields, path, label, geometry)
    if resolved is not None:
        header.width, header.height, header.geometry_source = resolved
    return header


def format_header(encoding: str, width: int, height: int, extra: dict[str, str] | None = None) -> bytes:
    """A header the vendor's tools read: ``% evt``, ``% format``, ``% geometry``, extra lines, ``% end``."""
    version = {"EVT3": "3.0", "EVT2": "2.0"}[encoding]
    lines = [f"% evt {version}", f"% format {encoding};height={height};width={width}", f"% geometry {width}x{height}"]
    lines += [f"% {key} {value}" for key, value in (extra or {}).items()]
    lines.append("% end")
    return ("\n".join(lines) + "\n").encode("ascii")


def read_header(
    path: str | os.PathLike[str], *, label: str = "RAW", geometry: tuple[int, int] | None = None
) -> RawHeader:
    """Parse the header of the file at ``path`` (``geometry`` overriding the declared one); a missing
    file is a FormatError."""
    path = Path(path)
    if not path.is_file():
        raise FormatError(path, "no such file" if not path.exists() else "not a file")
    with open(path, "rb") as fh:
        return parse_header(fh, path, label=label, geometry=geometry)


def read_sized_header(
    path: Path, encoding: str, label: str, geometry: tuple[int, int] | None = None
) -> tuple[RawHeader, int, int]:
    """The header of a RAW file that must be ``encoding`` (or undeclared) and have a sensor size
    (declared, implied or the ``geometry`` given): the header, width and height; a FormatError naming
    ``label`` (e.g. "EVT 3.0") otherwise."""
    header = read_header(path, geometry=geometry)
    if header.encoding not in (None, encoding):
        raise FormatError(path, f"RAW file is {header.encoding}, not {label}")
    if header.width is None or header.height is None:
        raise FormatError(path, missing_geometry(header))
    return header, int(header.width), int(header.height)


@dataclass
class DecodeStats:
    """What a RAW (or DAT) decoder met besides events: words skipped by reason, events dropped, a cut-off tail.

    Skipped words are never guessed at: ``others`` (OTHERS/CONTINUED, defined but not events),
    ``unknown`` (word types the encoding does not define), ``no_time`` (events or triggers before the
    first TIME_HIGH), ``no_y`` (events before the first ADDR_Y), ``no_base`` (vectors before the first
    VECT_BASE_X); ``outside`` counts events beyond the header's geometry; ``bad_polarity`` DAT records
    whose polarity is neither 0 nor 1; ``trailing_bytes`` a last partial word at ``trailing_offset`` (a
    truncated file). ``unit`` names the file's items in ``summary`` ("word", or "record" for DAT).
    """

    words: int = 0
    events: int = 0
    triggers: int = 0
    others: int = 0
    unknown: int = 0
    no_time: int = 0
    no_y: int = 0
    no_base: int = 0
    outside: int = 0
    trailing_bytes: int = 0
    trailing_offset: int | None = None
    bad_polarity: int = 0
    unit: str = "word"

    COUNTERS = ("others", "unknown", "no_time", "no_y", "no_base", "outside")

    def add_counters(self, counters: np.ndarray) -> None:
        for name, value in zip(self.COUNTERS, counters):
            setattr(self, name, getattr(self, name) + int(value))

    @property
    def clean(self) -> bool:
        return not (
            self.unknown or self.no_time or self.no_y or self.no_base or self.outside or self.bad_polarity or self.trailing_bytes
        )

    def summary(self) -> str:
        """One line: events and triggers decoded, then every non-zero skip counter."""
        labels = {
            "others": "OTHERS/CONTINUED words skipped",
            "unknown": "words of unknown type skipped",
            "no_time": "words before the first TIME_HIGH skipped",
            "no_y": "event words before the first ADDR_Y skipped",
            "no_base": "vector words without VECT_BASE_X skipped",
            "outside": "events outside the sensor geometry dropped",
            "bad_polarity": "records with a polarity other than 0 or 1 skipped",
        }
        parts = [f"{self.events:,} events, {self.triggers:,} triggers from {self.words:,} {self.unit}s"]
        parts += [f"{getattr(self, k):,} {text}" for k, text in labels.items() if getattr(self, k)]
        if self.trailing_bytes:
            parts.append(
                f"{self.trailing_bytes} trailing byte(s) of a cut-off {self.unit} at byte {self.trailing_offset} ignored"
            )
        return "; ".join(parts)


def iter_words(
    path: Path, header: RawHeader, dtype: str | np.dtype, chunk_words: int, stats: DecodeStats
) -> Iterator[tuple[int, np.ndarray]]:
    """Yield (byte offset, words) blocks of the data after the header in bounded memory; a last
    partial word is recorded in ``stats`` rather than decoded."""
    itemsize = int(np.dtype(dtype).itemsize)
    with open(path, "rb") as fh:
        fh.seek(header.data_offset)
        offset = header.data_offset
        while True:
            block = fh.read(chunk_words * itemsize)
            if not block:
                return
            usable = len(block) - len(block) % itemsize
            if usable < len(block):
                stats.trailing_bytes = len(block) - usable
                stats.trailing_offset = offset + usable
            if usable:
                words = np.frombuffer(block, dtype=dtype, count=usable // itemsize)
                stats.words += len(words)
                yield offset, words
            offset += len(block)


def concat_triggers(parts: list[Triggers]) -> Triggers:
    """One trigger table from blocks in order (an empty table for none)."""
    cols = ("t", "channel", "value")
    if not parts:
        return Triggers(np.empty(0, np.int64), np.empty(0, np.uint8), np.empty(0, np.int8))
    return Triggers(*(np.concatenate([getattr(p, c) for p in parts]) for c in cols))
