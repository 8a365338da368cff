"""Prophesee EVT 3.0: decoding RAW files into event streams and encoding streams back, bit-exactly.

Words are 16-bit little-endian with the type in bits 15..12 (see ``docs/event-files.md``). The
decoder keeps the vendor's production semantics: a TIME_HIGH equal to the previous one keeps the
low bits, a changed one resets them; a wrap of the 24-bit time is counted when the new TIME_HIGH is
at least 2048 below the previous one, so a small backward TIME_LOW or TIME_HIGH step is taken as it
is, not as a wrap; vectors add their set bits to the current VECT_BASE_X, which then advances by
12 or 8. Words that carry no event are skipped and counted in ``DecodeStats``, never guessed at.

Two engines give identical results: a compiled loop (numba, when installed; ``PSFMT_NUMBA=0``
turns it off) and a vectorised numpy path that needs nothing beyond numpy; ``engine="auto"`` takes
the compiled one when it is there. The encoder writes TIME_HIGH/TIME_LOW/ADDR_Y only when they
change and runs of at least ``VECTOR_MIN_EVENTS`` events of one row, time and polarity within 32
pixels as a VECT_BASE_X followed by the triplet VECT_12, VECT_12, VECT_8 that the vendor's decoder
expects; both engines write the same bytes, whatever the block boundaries.

The word layout, the engine choice and both kernels live in ``psfmt.eventfiles._evt3``; this module streams
files and blocks through them.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from psfmt.atomic import atomic_path
from psfmt.errors import FormatError
from psfmt.eventfiles._evt3.decoding import DECODER_STATE, Output, decode_into, decode_numba, decode_numpy, decode_parallel, skip_words, state_time_us
from psfmt.eventfiles._evt3.encoding import ENCODER_STATE, encode_numba, encode_numpy
from psfmt.eventfiles._evt3.engine import resolve, usable_cores
from psfmt.eventfiles._evt3.words import (
    MAX_COORD,
)
from psfmt.eventfiles.rawheader import (
    DecodeStats,
    concat_triggers,
    format_header,
    iter_words,
    read_sized_header,
)
from psfmt.events import EventArray, Triggers

DEFAULT_CHUNK_WORDS = 1 << 22
PARALLEL_MIN_WORDS = 1 << 18
"""Blocks of at least this many words are decoded on two threads by ``Evt3File.read``."""


@dataclass
class Decoder:
    """A streaming EVT 3.0 decoder: feed word blocks in order, get events and triggers per block.

    ``width``/``height`` bound the accepted coordinates (events outside are dropped and counted).
    """

    width: int = MAX_COORD + 1
    height: int = MAX_COORD + 1
    engine: str = "auto"
    stats: DecodeStats = field(default_factory=DecodeStats)

    def __post_init__(self) -> None:
        self.engine = resolve(self.engine)
        self.state = np.array(DECODER_STATE, dtype=np.int64)

    def feed(self, words: np.ndarray) -> tuple[EventArray, Triggers]:
        counters = np.zeros(6, np.int64)
        decode = decode_numba if self.engine == "numba" else decode_numpy
        events, triggers = decode(np.asarray(words, dtype=np.uint16), self.state, counters, self.width, self.height)
        self.stats.add_counters(counters)
        self.stats.events += len(events)
        self.stats.triggers += len(triggers)
        return events, triggers

    @property
    def time_us(self) -> int | None:
        """The time the stream has reached (None before the first TIME_HIGH)."""
        return state_time_us(self.state)

    def skip(self, words: np.ndarray) -> None:
        """Advance the state over ``words`` without producing events (for time windows)."""
        skip_words(np.asarray(words, dtype=np.uint16), self.state)


def decode(
    data: bytes | np.ndarray, width: int = MAX_COORD + 1, height: int = MAX_COORD + 1, *, engine: str = "auto"
) -> tuple[EventArray, Triggers, DecodeStats]:
    """Decode EVT 3.0 words (bytes without header, or a uint16 array) in one go."""
    words = np.frombuffer(data, dtype="<u2", count=len(data) // 2) if isinstance(data, (bytes, bytearray, memoryview)) else data
    decoder = Decoder(width, height, engine)
    decoder.stats.words = len(words)
    events, triggers = decoder.feed(words)
    return events, triggers, decoder.stats


class Evt3File:
    """An EVT 3.0 RAW file, decoded in bounded memory: ``chunks()`` streams it, ``window()`` decodes
    only the words around a time range, ``read()`` decodes everything (with numba, into one output
    and on two threads where two cores are usable); ``stats`` sums up the last pass.
    The sensor size is the header's (``psfmt.eventfiles.rawheader.resolve_geometry``) unless ``geometry`` gives it."""

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        engine: str = "auto",
        chunk_words: int = DEFAULT_CHUNK_WORDS,
        geometry: tuple[int, int] | None = None,
    ) -> None:
        self.path = Path(path)
        self.header, self.width, self.height = read_sized_header(self.path, "EVT3", "EVT 3.0", geometry)
        self.engine = resolve(engine)
        self.chunk_words = int(chunk_words)
        self.stats = DecodeStats()

    def _decoder(self) -> Decoder:
        self.stats = DecodeStats()
        return Decoder(self.width, self.height, self.engine, self.stats)

    def chunks(self) -> Iterator[tuple[EventArray, Triggers]]:
        """(events, triggers) per block of ``chunk_words`` words, in file order."""
        decoder = self._decoder()
        for _, words in iter_words(self.path, self.header, "<u2", self.chunk_words, self.stats):
            yield decoder.feed(words)

    def read(self) -> tuple[EventArray, Triggers]:
        if self.engine == "numba":
            # one output for the whole file, sized at a word per event (sensors write more words
            # than events) and grown if need be; large blocks decoded on two threads where there are
            # two cores
            decoder = self._decoder()
            out = Output((self.path.stat().st_size - self.header.data_offset) // 2 + 12)
            parallel = usable_cores() > 1
            for _, words in iter_words(self.path, self.header, "<u2", self.chunk_words, self.stats):
                counters = np.zeros(6, np.int64)
                decode = decode_parallel if parallel and len(words) >= PARALLEL_MIN_WORDS else decode_into
                decode(words, decoder.state, counters, self.width, self.height, out)
                self.stats.add_counters(counters)
            events, triggers = out.take()
            self.stats.events, self.stats.triggers = len(events), len(triggers)
            return events, triggers
        parts = list(self.chunks())
        return EventArray.concatenate([e for e, _ in parts]), concat_triggers([t for _, t in parts])

    def window(self, t0_us: int, t1_us: int) -> EventArray:
        """Events with ``t0_us <= t < t1_us``. Blocks that end before the window only advance the
        decoder state and reading stops once the stream is past the window, assuming (as every
        sensor writes them) that times never step back by more than one TIME_HIGH period (4096 µs)."""
        decoder = self._decoder()
        slack = 1 << 12
        parts = []
        for _, words in iter_words(self.path, self.header, "<u2", self.chunk_words, self.stats):
            probe = decoder.state.copy()
            decoder.skip(words)
            end = decoder.time_us
            if end is None or end < t0_us - slack:
                continue
            decoder.state[:] = probe
            events, _ = decoder.feed(words)
            keep = (events.t >= t0_us) & (events.t < t1_us)
            parts.append(events[keep])
            if end >= t1_us + slack:
                break
        return EventArray.concatenate(parts)


def _check_encodable(events: EventArray, last_t_us: int | None) -> None:
    """ValueError unless ``events`` fit EVT 3.0 after an event at ``last_t_us``: times ≥ 0 µs, sorted
    and not before ``last_t_us``, x and y at most ``MAX_COORD``."""
    if len(events) == 0:
        return
    if int(events.t[0]) < 0:
        raise ValueError(f"EVT 3.0 cannot hold negative times (first event at {int(events.t[0])} µs)")
    if not events.is_sorted() or (last_t_us is not None and int(events.t[0]) < last_t_us):
        raise ValueError("EVT 3.0 encoding needs events sorted by time")
    if int(events.x.max()) > MAX_COORD or int(events.y.max()) > MAX_COORD:
        raise ValueError(f"EVT 3.0 coordinates are 11-bit: x and y must be at most {MAX_COORD}")


class Encoder:
    """A streaming EVT 3.0 encoder: ``feed`` sorted event blocks in order, ``finish`` at the end.

    Events sharing the last time of a block are held back until the next block, so the bytes do not
    depend on how the stream was cut into blocks."""

    def __init__(self, engine: str = "auto") -> None:
        self.engine = resolve(engine)
        self.state = np.array(ENCODER_STATE, dtype=np.int64)
        self._held = EventArray.empty()
        self._last: int | None = None

    def _encode(self, events: EventArray) -> bytes:
        if len(events) == 0:
            return b""
        encode = encode_numba if self.engine == "numba" else encode_numpy
        return encode(events.x, events.y, events.t, events.p, self.state).astype("<u2").tobytes()

    def feed(self, events: EventArray) -> bytes:
        _check_encodable(events, self._last)
        if len(events) == 0:
            return b""
        self._last = int(events.t[-1])
        block = EventArray.concatenate([self._held, events]) if len(self._held) else events
        cut = int(np.searchsorted(block.t, block.t[-1], side="left"))
        self._held = block[cut:]
        return self._encode(block[:cut])

    def finish(self) -> bytes:
        held, self._held = self._held, EventArray.empty()
        return self._encode(held)


def encode(events: EventArray, *, engine: str = "auto") -> bytes:
    """EVT 3.0 words (no header) for sorted events; ``decode(encode(e))`` gives ``e`` back exactly."""
    encoder = Encoder(engine)
    return encoder.feed(events) + encoder.finish()


def encoded_size(chunks: Iterable[EventArray], *, engine: str = "auto") -> int:
    """Bytes of the EVT 3.0 encoding of a stream given block by block (header not counted)."""
    encoder = Encoder(engine)
    return sum(len(encoder.feed(c)) for c in chunks) + len(encoder.finish())


def write_raw(
    path: str | os.PathLike[str],
    chunks: Iterable[EventArray],
    width: int,
    height: int,
    *,
    header: dict[str, str] | None = None,
    engine: str = "auto",
) -> Path:
    """Write an EVT 3.0 RAW file (header and words) from sorted event blocks, atomically."""
    path = Path(path)
    if width > MAX_COORD + 1 or height > MAX_COORD + 1:
        raise FormatError(path, f"EVT 3.0 holds sensors up to {MAX_COORD + 1}×{MAX_COORD + 1}, not {width}×{height}")
    encoder = Encoder(engine)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(format_header("EVT3", width, height, header))
        for block in chunks:
            fh.write(encoder.feed(block))
        fh.write(encoder.finish())
    return path
