"""Prophesee EVT 2.0: 32-bit little-endian words, type in bits 31..28, vectorised with numpy.

CD_OFF (0x0) / CD_ON (0x1) carry y in bits 10..0, x in 21..11 and time bits 5..0 in 27..22;
TIME_HIGH (0x8) carries time bits 33..6; EXT_TRIGGER (0xA) the value in bit 0, the channel in bits
12..8 and time bits 5..0 in 27..22; OTHERS (0xE) and CONTINUED (0xF) are skipped and counted.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from psfmt.atomic import atomic_path
from psfmt.errors import FormatError
from psfmt.eventfiles.rawheader import (
    DecodeStats,
    concat_triggers,
    format_header,
    iter_words,
    read_sized_header,
)
from psfmt.events import EventArray, Triggers

CD_OFF, CD_ON, TIME_HIGH, EXT_TRIGGER = 0x0, 0x1, 0x8, 0xA
SKIPPED_TYPES = (0xE, 0xF)
MAX_COORD = 2047
DEFAULT_CHUNK_WORDS = 1 << 21


@dataclass
class Decoder:
    """A streaming EVT 2.0 decoder: feed word blocks in order; the TIME_HIGH carries over blocks."""

    width: int = MAX_COORD + 1
    height: int = MAX_COORD + 1
    stats: DecodeStats = field(default_factory=DecodeStats)
    time_high: int = -1

    def feed(self, words: np.ndarray) -> tuple[EventArray, Triggers]:
        w = np.asarray(words, dtype=np.uint32).astype(np.int64)
        typ = w >> 28
        is_th = typ == TIME_HIGH
        last = np.maximum.accumulate(np.where(is_th, np.arange(len(w)), -1))
        high = np.where(last >= 0, w[np.maximum(last, 0)] & 0x0FFFFFFF, self.time_high)
        t = (high << 6) | ((w >> 22) & 0x3F)
        known = high >= 0
        is_cd = (typ == CD_OFF) | (typ == CD_ON)
        is_trig = typ == EXT_TRIGGER
        x, y = (w >> 11) & 0x7FF, w & 0x7FF
        inside = (x < self.width) & (y < self.height)
        keep = is_cd & known & inside
        trig = is_trig & known
        counters = np.array(
            [
                np.isin(typ, SKIPPED_TYPES).sum(),
                (~(is_cd | is_trig | is_th | np.isin(typ, SKIPPED_TYPES))).sum(),
                ((is_cd | is_trig) & ~known).sum(),
                0,
                0,
                (is_cd & known & ~inside).sum(),
            ]
        )
        self.stats.add_counters(counters)
        if len(w):
            self.time_high = int(high[-1])
        events = EventArray(x[keep], y[keep], t[keep], np.where(typ[keep] == CD_ON, 1, -1))
        triggers = Triggers(t[trig], (w[trig] >> 8) & 0x1F, w[trig] & 1)
        self.stats.events += len(events)
        self.stats.triggers += len(triggers)
        return events, triggers


def decode(data: bytes | np.ndarray, width: int = MAX_COORD + 1, height: int = MAX_COORD + 1) -> tuple[EventArray, Triggers, DecodeStats]:
    """Decode EVT 2.0 words (bytes without header, or a uint32 array) in one go."""
    words = np.frombuffer(data, dtype="<u4", count=len(data) // 4) if isinstance(data, (bytes, bytearray, memoryview)) else data
    decoder = Decoder(width, height)
    decoder.stats.words = len(words)
    events, triggers = decoder.feed(words)
    return events, triggers, decoder.stats


def encode(events: EventArray, time_high: int = -1) -> tuple[bytes, int]:
    """EVT 2.0 words for sorted events (a TIME_HIGH whenever time bits 33..6 change, then one CD
    word per event) and the last TIME_HIGH written, to carry into the next block."""
    if len(events) == 0:
        return b"", time_high
    t = events.t
    if int(t[0]) < 0 or int(t[-1]) >= 1 << 34:
        raise ValueError("EVT 2.0 times must lie in [0, 2^34) µs")
    if not events.is_sorted():
        raise ValueError("EVT 2.0 encoding needs events sorted by time")
    if int(events.x.max()) > MAX_COORD or int(events.y.max()) > MAX_COORD:
        raise ValueError(f"EVT 2.0 coordinates are 11-bit: x and y must be at most {MAX_COORD}")
    high = t >> 6
    new = np.empty(len(t), bool)
    new[0] = high[0] != time_high
    new[1:] = high[1:] != high[:-1]
    cd = (
        (np.where(events.p > 0, CD_ON, CD_OFF).astype(np.int64) << 28)
        | ((t & 0x3F) << 22)
        | (events.x.astype(np.int64) << 11)
        | events.y.astype(np.int64)
    )
    out = np.empty(len(t) + int(new.sum()), dtype=np.int64)
    position = np.arange(len(t)) + np.cumsum(new)
    out[position] = cd
    out[position[new] - 1] = (TIME_HIGH << 28) | high[new]
    return out.astype("<u4").tobytes(), int(high[-1])


class Evt2File:
    """An EVT 2.0 RAW file decoded in bounded memory (``chunks``) or at once (``read``); the sensor size
    is the header's unless ``geometry`` gives it."""

    def __init__(
        self, path: str | os.PathLike[str], *, chunk_words: int = DEFAULT_CHUNK_WORDS, geometry: tuple[int, int] | None = None
    ) -> None:
        self.path = Path(path)
        self.header, self.width, self.height = read_sized_header(self.path, "EVT2", "EVT 2.0", geometry)
        self.chunk_words = int(chunk_words)
        self.stats = DecodeStats()

    def chunks(self) -> Iterator[tuple[EventArray, Triggers]]:
        self.stats = DecodeStats()
        decoder = Decoder(self.width, self.height, self.stats)
        for _, words in iter_words(self.path, self.header, "<u4", self.chunk_words, self.stats):
            yield decoder.feed(words)

    def read(self) -> tuple[EventArray, Triggers]:
        parts = list(self.chunks())
        events = EventArray.concatenate([e for e, _ in parts])
        return events, concat_triggers([t for _, t in parts])


def write_raw(path: str | os.PathLike[str], chunks: Iterable[EventArray], width: int, height: int) -> Path:
    """Write an EVT 2.0 RAW file (header and words) from sorted event blocks, atomically."""
    path = Path(path)
    if width > MAX_COORD + 1 or height > MAX_COORD + 1:
        raise FormatError(path, f"EVT 2.0 holds sensors up to {MAX_COORD + 1}×{MAX_COORD + 1}, not {width}×{height}")
    time_high = -1
    last: int | None = None
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(format_header("EVT2", width, height))
        for block in chunks:
            if len(block) and last is not None and int(block.t[0]) < last:
                raise ValueError("EVT 2.0 encoding needs events sorted by time")
            data, time_high = encode(block, time_high)
            last = block.t_last_us if len(block) else last
            fh.write(data)
    return path
