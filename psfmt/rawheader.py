"""The ASCII header of Prophesee RAW files (EVT 2.0 / EVT 3.0): ``% key value`` lines before the data.

The data begins at the first line that does not start with ``% `` (or right after ``% end``), as the
vendor's readers define it; the sensor geometry comes from ``% geometry WxH``, the ``% format``
line's ``width=``/``height=`` fields, or the older ``% Width`` / ``% Height`` lines.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

import numpy as np

from psfmt.errors import FormatError
from psfmt.events import Triggers
from psfmt.limits import MAX_SENSOR_SIDE

MAX_HEADER_BYTES = 1 << 20


@dataclass
class RawHeader:
    """A parsed RAW header: ``fields`` in file order (key → value text), geometry, encoding, data offset."""

    fields: dict[str, str] = field(default_factory=dict)
    width: int | None = None
    height: int | None = None
    encoding: str | None = None
    data_offset: int = 0


def _declared_geometry(fields: dict[str, str], path: Path) -> tuple[int | None, int | None]:
    try:
        if "geometry" in fields:
            w, h = fields["geometry"].lower().split("x")
            return int(w), int(h)
        fmt = dict(
            part.split("=", 1) for part in fields.get("format", "").split(";")[1:] if "=" in part
        )
        if "width" in fmt and "height" in fmt:
            return int(fmt["width"]), int(fmt["height"])
        if "Width" in fields and "Height" in fields:
            return int(fields["Width"]), int(fields["Height"])
    except ValueError:
        raise FormatError(path, "RAW header has an unreadable sensor geometry") from None
    return None, None


def _geometry(fields: dict[str, str], path: Path) -> tuple[int | None, int | None]:
    """The declared sensor size, each side within 1…65536 pixels (what a capture's uint16 holds)."""
    width, height = _declared_geometry(fields, path)
    if width is not None and height is not None and not (0 < width <= MAX_SENSOR_SIDE and 0 < height <= MAX_SENSOR_SIDE):
        raise FormatError(path, f"RAW header declares a {width}×{height} sensor; each side must be 1…{MAX_SENSOR_SIDE} pixels")
    return width, height


def _encoding(fields: dict[str, str]) -> str | None:
    fmt = fields.get("format", "").split(";")[0].strip().upper()
    if fmt in ("EVT3", "EVT2", "EVT21"):
        return fmt
    evt = fields.get("evt", "").strip()
    return {"3.0": "EVT3", "2.0": "EVT2", "2.1": "EVT21"}.get(evt)


def parse_header(fh: BinaryIO, path: str | os.PathLike[str]) -> RawHeader:
    """Read the header from the start of ``fh`` and leave ``fh`` at the first data byte."""
    path = Path(path)
    fields: dict[str, str] = {}
    offset = 0
    fh.seek(0)
    while True:
        if offset > MAX_HEADER_BYTES:
            raise FormatError(path, f"RAW header longer than {MAX_HEADER_BYTES} bytes (not a RAW file?)")
        start = fh.read(2)
        if start != b"% ":
            break
        line = b"% " + fh.readline(MAX_HEADER_BYTES)
        offset += len(line)
        text = line[2:].decode("ascii", errors="replace").strip()
        key, _, value = text.partition(" ")
        if key == "end":
            break
        if key:
            fields[key] = value.strip()
    fh.seek(offset)
    width, height = _geometry(fields, path)
    return RawHeader(fields, width, height, _encoding(fields), offset)


def format_header(encoding: str, width: int, height: int, extra: dict[str, str] | None = None) -> bytes:
    """A header the vendor's tools read: ``% evt``, ``% format``, ``% geometry``, extra lines, ``% end``."""
    version = {"EVT3": "3.0", "EVT2": "2.0"}[encoding]
    lines = [f"% evt {version}", f"% format {encoding};height={height};width={width}", f"% geometry {width}x{height}"]
    lines += [f"% {key} {value}" for key, value in (extra or {}).items()]
    lines.append("% end")
    return ("\n".join(lines) + "\n").encode("ascii")


def read_header(path: str | os.PathLike[str]) -> RawHeader:
    """Parse the header of the RAW file at ``path``; a missing file is a FormatError."""
    path = Path(path)
    if not path.is_file():
        raise FormatError(path, "no such file" if not path.exists() else "not a file")
    with open(path, "rb") as fh:
        return parse_header(fh, path)


def read_sized_header(path: Path, encoding: str, label: str) -> tuple[RawHeader, int, int]:
    """The header of a RAW file that must be ``encoding`` (or undeclared) and declare its sensor size:
    the header, width and height; a FormatError naming ``label`` (e.g. "EVT 3.0") otherwise."""
    header = read_header(path)
    if header.encoding not in (None, encoding):
        raise FormatError(path, f"RAW file is {header.encoding}, not {label}")
    if header.width is None or header.height is None:
        raise FormatError(path, "RAW header declares no sensor geometry (% geometry WxH)")
    return header, int(header.width), int(header.height)


@dataclass
class DecodeStats:
    """What a RAW decoder met besides events: words skipped by reason, events dropped, a cut-off tail.

    Skipped words are never guessed at: ``others`` (OTHERS/CONTINUED, defined but not events),
    ``unknown`` (word types the encoding does not define), ``no_time`` (events or triggers before the
    first TIME_HIGH), ``no_y`` (events before the first ADDR_Y), ``no_base`` (vectors before the first
    VECT_BASE_X); ``outside`` counts events beyond the header's geometry; ``trailing_bytes`` a last
    partial word at ``trailing_offset`` (a truncated file).
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

    COUNTERS = ("others", "unknown", "no_time", "no_y", "no_base", "outside")

    def add_counters(self, counters: np.ndarray) -> None:
        for name, value in zip(self.COUNTERS, counters):
            setattr(self, name, getattr(self, name) + int(value))

    @property
    def clean(self) -> bool:
        return not (self.unknown or self.no_time or self.no_y or self.no_base or self.outside or self.trailing_bytes)

    def summary(self) -> str:
        """One line: events and triggers decoded, then every non-zero skip counter."""
        labels = {
            "others": "OTHERS/CONTINUED words skipped",
            "unknown": "words of unknown type skipped",
            "no_time": "words before the first TIME_HIGH skipped",
            "no_y": "event words before the first ADDR_Y skipped",
            "no_base": "vector words without VECT_BASE_X skipped",
            "outside": "events outside the sensor geometry dropped",
        }
        parts = [f"{self.events:,} events, {self.triggers:,} triggers from {self.words:,} words"]
        parts += [f"{getattr(self, k):,} {text}" for k, text in labels.items() if getattr(self, k)]
        if self.trailing_bytes:
            parts.append(f"{self.trailing_bytes} trailing byte(s) of a cut-off word at byte {self.trailing_offset} ignored")
        return "; ".join(parts)


def iter_words(
    path: Path, header: RawHeader, dtype: str, chunk_words: int, stats: DecodeStats
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
