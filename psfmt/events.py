"""Event streams in memory and on disk, and the millisecond index that makes time windows cheap.

An event is (x, y, t, p): pixel column and row (uint16), time in int64 microseconds, polarity int8 ±1.
Streams are sorted by t. On disk the four columns are separate chunked datasets and ``ms_to_idx``
holds, for every millisecond boundary ``b_i = ms_origin_us + 1000·i``, the number of events with
``t < b_i`` (the DSEC ``ms_to_idx`` idea), so a window is read by slicing, never by scanning.

Every event stream — ``EventArray`` in memory, ``H5EventStore`` on disk and ``Events``, the stream
with its sensor size that a capture holds — has ``len``, slicing by event index (``ev[0:10]``) and
``window(t0_us, t1_us)``, which raises ValueError when ``t1_us < t0_us``.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from psfmt.describe import path_text
from psfmt.files import hdf5_errors, require_open
from psfmt.inflate import ColumnReader

EVENT_DTYPES: dict[str, np.dtype[Any]] = {
    "x": np.dtype(np.uint16),
    "y": np.dtype(np.uint16),
    "t": np.dtype(np.int64),
    "p": np.dtype(np.int8),
}
DEFAULT_CHUNK_EVENTS = 1 << 16


def check_window(t0_us: int, t1_us: int) -> tuple[int, int]:
    """The window ``[t0_us, t1_us)`` as two ints; ValueError when it ends before it starts (a window
    given backwards would otherwise read as empty, which hides the mistake). ``t0_us == t1_us`` is an
    empty window."""
    t0, t1 = int(t0_us), int(t1_us)
    if t1 < t0:
        raise ValueError(f"event window [{t0}, {t1}) µs ends before it starts: give t0_us <= t1_us (events with t0_us <= t < t1_us)")
    return t0, t1


def _slice_only(index: object, what: str) -> slice:
    """``index`` when it is a slice; TypeError otherwise (one event is ``ev[i:i+1]``)."""
    if not isinstance(index, slice):
        raise TypeError(f"{what} are indexed by a slice of event indices (ev[i:j]; one event is ev[i:i+1]), not {type(index).__name__}")
    return index


@dataclass
class EventArray:
    """Events held in memory as four equal-length columns sorted by ``t`` (µs): ``x``, ``y`` uint16
    pixel column and row, ``t`` int64 µs, ``p`` int8 polarity ±1. ``len`` is the number of events;
    indexing by a slice (``ev[0:10]``), a boolean mask or an index array gives an ``EventArray``."""

    x: np.ndarray
    y: np.ndarray
    t: np.ndarray
    p: np.ndarray

    def __post_init__(self) -> None:
        self.x = np.ascontiguousarray(self.x, dtype=np.uint16)
        self.y = np.ascontiguousarray(self.y, dtype=np.uint16)
        self.t = np.ascontiguousarray(self.t, dtype=np.int64)
        self.p = np.ascontiguousarray(self.p, dtype=np.int8)
        n = len(self.t)
        if not (len(self.x) == len(self.y) == len(self.p) == n) or self.t.ndim != 1:
            raise ValueError("event columns x, y, t, p must be 1-D and of equal length")

    @classmethod
    def empty(cls) -> EventArray:
        return cls(*(np.empty(0, dtype=d) for d in EVENT_DTYPES.values()))

    @classmethod
    def concatenate(cls, parts: list[EventArray]) -> EventArray:
        if not parts:
            return cls.empty()
        return cls(*(np.concatenate([getattr(e, c) for e in parts]) for c in "xytp"))

    def __len__(self) -> int:
        return len(self.t)

    def __getitem__(self, index: slice | np.ndarray) -> EventArray:
        """The events at ``index`` (a slice, a boolean mask or an index array); TypeError for a single
        integer, which would give a scalar per column (one event is ``ev[i:i+1]``)."""
        if isinstance(index, (int, np.integer)):
            raise TypeError("events are indexed by a slice, a boolean mask or an index array (one event is ev[i:i+1]), not an integer")
        return EventArray(self.x[index], self.y[index], self.t[index], self.p[index])

    def __repr__(self) -> str:
        # one line whatever the count: the columns can hold millions of events
        span = f", t {self.t[0]}…{self.t[-1]} µs" if len(self.t) else ""
        return f"EventArray({len(self)} events{span})"

    @property
    def t_first_us(self) -> int | None:
        return int(self.t[0]) if len(self.t) else None

    @property
    def t_last_us(self) -> int | None:
        return int(self.t[-1]) if len(self.t) else None

    def window(self, t0_us: int, t1_us: int) -> EventArray:
        """Events with ``t0_us <= t < t1_us`` (µs); ValueError when ``t1_us < t0_us``."""
        t0, t1 = check_window(t0_us, t1_us)
        lo, hi = np.searchsorted(self.t, [t0, t1], side="left")
        return self[lo:hi]

    def chunks(self, size: int = 1 << 20) -> Iterator[EventArray]:
        for start in range(0, len(self), size):
            yield self[start : start + size]

    def read(self) -> EventArray:
        return self

    def is_sorted(self) -> bool:
        return bool(np.all(self.t[1:] >= self.t[:-1]))

    def to_structured(self) -> np.ndarray:
        """A structured array with fields x, y, t, p (the layout of tonic and most event libraries)."""
        out = np.empty(len(self), dtype=[("x", "<u2"), ("y", "<u2"), ("t", "<i8"), ("p", "i1")])
        for c in "xytp":
            out[c] = getattr(self, c)
        return out


def ms_origin(t_first_us: int | None) -> int:
    """Index origin: the first event's time rounded down to a whole millisecond (0 for no events)."""
    return 0 if t_first_us is None else (int(t_first_us) // 1000) * 1000


def ms_index_length(t_first_us: int | None, t_last_us: int | None) -> int:
    """Entries of ``ms_to_idx``: boundaries from the origin up to the first one after the last event."""
    if t_first_us is None or t_last_us is None:
        return 1
    return (int(t_last_us) - ms_origin(t_first_us)) // 1000 + 2


class MsIndexBuilder:
    """Builds ``ms_to_idx`` from sorted blocks of times as they stream past, in bounded memory.

    An entry is final once an event at or after its boundary has been seen, since every later event
    is later still; ``finish`` fills the boundaries after the last event with the total count.
    """

    def __init__(self) -> None:
        self.t_first_us: int | None = None
        self.t_last_us: int | None = None
        self._parts: list[np.ndarray] = []
        self._done = 0
        self._count = 0

    @property
    def origin_us(self) -> int:
        return ms_origin(self.t_first_us)

    def add(self, t_us: np.ndarray) -> None:
        if len(t_us) == 0:
            return
        if self.t_first_us is None:
            self.t_first_us = int(t_us[0])
        complete = (int(t_us[-1]) - self.origin_us) // 1000 + 1
        if complete > self._done:
            bounds = self.origin_us + 1000 * np.arange(self._done, complete, dtype=np.int64)
            self._parts.append((self._count + np.searchsorted(t_us, bounds, side="left")).astype(np.uint64))
            self._done = complete
        self.t_last_us = int(t_us[-1])
        self._count += len(t_us)

    def take(self) -> np.ndarray:
        """The entries made final since the last ``take`` (a scan compares them as it goes)."""
        parts, self._parts = self._parts, []
        return np.concatenate(parts) if parts else np.empty(0, np.uint64)

    def finish(self) -> np.ndarray:
        """The entries not taken yet, through the end of the index."""
        length = ms_index_length(self.t_first_us, self.t_last_us)
        tail = np.full(length - self._done, self._count, dtype=np.uint64)
        return np.concatenate(self._parts + [tail])


class H5EventStore:
    """Events in an open HDF5 group, read lazily: by window through the index, or chunk by chunk."""

    def __init__(self, group: Any) -> None:
        self._group = group
        self._path = group.file.filename
        self._cols = {c: group[c] for c in "xytp"}
        self._readers = {c: ColumnReader(ds) for c, ds in self._cols.items()}
        self._n = int(self._cols["t"].shape[0])
        self._index = group["ms_to_idx"] if "ms_to_idx" in group else None
        self._origin = int(group.attrs.get("ms_origin_us", 0))
        self._chunk = (self._cols["t"].chunks or (DEFAULT_CHUNK_EVENTS,))[0]

    def __len__(self) -> int:
        return self._n

    def __getitem__(self, index: slice) -> EventArray:
        """The events of a slice of event indices, read from the file (only the chunks that hold them)."""
        picked = range(*_slice_only(index, "events on disk").indices(self._n))
        if not picked:
            return EventArray.empty()
        lo, hi = min(picked[0], picked[-1]), max(picked[0], picked[-1]) + 1
        block = self._slice(lo, hi)
        # a step other than 1 reads the rows it spans, then picks from them in memory
        return block if picked.step == 1 else block[np.asarray(picked) - lo]

    def __repr__(self) -> str:
        # no file access: a repr must work on a closed file too
        return f"H5EventStore({self._n} events in {path_text(self._path)})"

    @property
    def t_first_us(self) -> int | None:
        return int(self._column("t", 0, 1)[0]) if self._n else None

    @property
    def t_last_us(self) -> int | None:
        return int(self._column("t", self._n - 1, self._n)[0]) if self._n else None

    def _column(self, c: str, lo: int, hi: int) -> np.ndarray:
        require_open(self._group, self._path)
        with hdf5_errors(self._path):
            return self._readers[c].read(lo, hi)

    def _slice(self, lo: int, hi: int, t: np.ndarray | None = None) -> EventArray:
        cols = {c: self._column(c, lo, hi) for c in "xyp"}
        return EventArray(t=self._column("t", lo, hi) if t is None else t, **cols)

    def _bound(self, t_us: int, round_up: bool) -> int:
        """An event index that brackets ``t_us`` from below (or above) using only the ms index."""
        length = int(self._index.shape[0])
        offset = t_us - self._origin
        i = -(-offset // 1000) if round_up else offset // 1000
        if i <= 0:
            return 0
        if i >= length:
            return self._n
        with hdf5_errors(self._path):
            # a stored entry beyond N (a file read without verify) must not widen the read
            return min(int(self._index[i]), self._n)

    def window(self, t0_us: int, t1_us: int) -> EventArray:
        """Events with ``t0_us <= t < t1_us`` (µs), reading only the chunks that hold them; ValueError
        when ``t1_us < t0_us``."""
        t0_us, t1_us = check_window(t0_us, t1_us)
        if self._n == 0 or t1_us == t0_us:
            return EventArray.empty()
        if self._index is None:
            lo, hi = 0, self._n
        else:
            lo, hi = self._bound(int(t0_us), False), self._bound(int(t1_us), True)
        t = self._column("t", lo, hi)
        a, b = (int(i) for i in np.searchsorted(t, [t0_us, t1_us], side="left"))
        return self._slice(lo + a, lo + b, t[a:b])

    def chunks(self, size: int | None = None) -> Iterator[EventArray]:
        """Bounded-memory iteration in time order; ``size`` defaults to a whole number of storage chunks."""
        step = size or 16 * self._chunk
        for start in range(0, self._n, step):
            yield self._slice(start, min(start + step, self._n))

    def read(self) -> EventArray:
        if self._n == 0:
            return EventArray.empty()
        return self._slice(0, self._n)


@dataclass
class Events:
    """An event stream with its sensor geometry (``width`` × ``height`` pixels); ``data`` is in memory
    or a lazy on-disk store. ``len`` is the number of events; a slice of event indices
    (``events[0:10]``) is an ``Events`` of the same sensor holding those events in memory."""

    width: int
    height: int
    data: EventArray | H5EventStore

    def __len__(self) -> int:
        return len(self.data)

    def __getitem__(self, index: slice) -> Events:
        return Events(self.width, self.height, self.data[_slice_only(index, "events")])

    def __repr__(self) -> str:
        where = "on disk" if isinstance(self.data, H5EventStore) else "in memory"
        span = f", t {self.data.t[0]}…{self.data.t[-1]} µs" if isinstance(self.data, EventArray) and len(self.data) else ""
        return f"Events({self.width}×{self.height}, {len(self.data)} events{span}, {where})"

    @property
    def t_first_us(self) -> int | None:
        return self.data.t_first_us

    @property
    def t_last_us(self) -> int | None:
        return self.data.t_last_us

    def window(self, t0_us: int, t1_us: int) -> EventArray:
        """Events with ``t0_us <= t < t1_us`` (µs); ValueError when ``t1_us < t0_us``."""
        return self.data.window(t0_us, t1_us)

    def chunks(self, size: int | None = None) -> Iterator[EventArray]:
        return self.data.chunks(size) if size else self.data.chunks()

    def read(self) -> EventArray:
        return self.data.read()


@dataclass
class Triggers:
    """External trigger edges (EVT EXT_TRIGGER): time µs, channel id, edge value 0/1."""

    t: np.ndarray
    channel: np.ndarray
    value: np.ndarray

    def __post_init__(self) -> None:
        self.t = np.ascontiguousarray(self.t, dtype=np.int64)
        self.channel = np.ascontiguousarray(self.channel, dtype=np.uint8)
        self.value = np.ascontiguousarray(self.value, dtype=np.int8)
        if not (len(self.t) == len(self.channel) == len(self.value)):
            raise ValueError("trigger columns t, channel, value must be of equal length")

    def __len__(self) -> int:
        return len(self.t)

    def __repr__(self) -> str:
        return f"Triggers({len(self)} edges)"

    def read(self) -> Triggers:
        return self


class H5Triggers:
    """The trigger table of an open HDF5 group, read when a column is first asked for (then kept)."""

    def __init__(self, group: Any) -> None:
        self._group = group
        self._path = group.file.filename
        self._n = int(group["t"].shape[0])
        self._table: Triggers | None = None

    def __len__(self) -> int:
        return self._n

    def __repr__(self) -> str:
        return f"H5Triggers({self._n} edges in {path_text(self._path)})"

    def read(self) -> Triggers:
        """The whole table in memory."""
        if self._table is None:
            require_open(self._group, self._path)
            with hdf5_errors(self._path):
                self._table = Triggers(*(self._group[c][()] for c in ("t", "channel", "value")))
        return self._table

    @property
    def t(self) -> np.ndarray:
        return self.read().t

    @property
    def channel(self) -> np.ndarray:
        return self.read().channel

    @property
    def value(self) -> np.ndarray:
        return self.read().value
