"""Metavision HDF5 event files (Metavision 4+'s ``.hdf5`` recordings), read in bounded memory.

The layout is OpenEB's ``hdf5_event_file_writer``: ``/CD/events`` a 1-D compound {x u16, y u16,
p i16, t i64 µs} dataset, chunked, normally compressed with Prophesee's ECF filter (HDF5 filter
0x8ECF, which h5py and hdf5plugin do not ship); ``/CD/indexes`` {id u64, ts i64} one entry per 2 ms
(entry k: the first event of the last non-empty 2 ms block before block k, ``ts`` relative to the
first event, the attribute ``offset`` = minus the first event's time); ``/EXT_TRIGGER/events``
{p i16, t i64, id i16}; the root attributes copy the camera's RAW header (``geometry``,
``format``, ``system_ID`` …), from which the sensor size is resolved as for RAW files.

ECF chunks are read raw (``read_direct_chunk``) and decoded by psfmt's own decoder
(``psfmt.eventfiles._ecf``: a compiled loop when numba is installed, split over threads, else whole-array
numpy), a batch of chunks at a time, so memory stays bounded whatever the file's length. A dataset
with no filter, or one HDF5 can apply (gzip, or what ``hdf5plugin`` registers when installed), is
read through h5py in the same batches. Nothing in the file is trusted: a chunk whose header counts
more events than its chunk holds, a chunk that ends before its events, coordinates beyond the
geometry, a time going back (within a chunk or from one to the next) or a polarity other than 0/1
is a one-line ``FormatError`` naming the file and the chunk; sizes are checked before allocating.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import h5py
import numpy as np

from psfmt.errors import FormatError
from psfmt.eventfiles._ecf.batch import decode_batch
from psfmt.eventfiles._ecf.chunk import FILTER_ID, MAX_CHUNK_EVENTS, MESSAGES, OK
from psfmt.eventfiles._evt3.engine import resolve, usable_cores
from psfmt.eventfiles.rawheader import RawHeader, missing_geometry, resolve_geometry
from psfmt.events import EventArray, Triggers, check_window
from psfmt.files import hdf5_errors, open_hdf5
from psfmt.limits import Limits
from psfmt.text import printable

try:  # registers the zstd/blosc/lz4 filters with HDF5 when present
    import hdf5plugin  # noqa: F401
except ImportError:  # pragma: no cover - exercised where hdf5plugin is absent
    pass

EVENTS, INDEXES, TRIGGERS = "/CD/events", "/CD/indexes", "/EXT_TRIGGER/events"
LABEL = "Metavision HDF5"
BATCH_EVENTS = 1 << 20
"""Events decoded per batch (rounded to whole chunks): what bounds the reader's memory."""
MAX_ATTRIBUTE_CHARS = 4096
FIELDS = {EVENTS: ("x", "y", "p", "t"), INDEXES: ("id", "ts"), TRIGGERS: ("p", "t", "id")}


def default_threads() -> int:
    """Threads that decode ECF chunks side by side: the cores this process may use, at most 8."""
    return max(1, min(8, usable_cores()))


def _text(value: object) -> str:
    if isinstance(value, bytes):
        value = value.decode("utf-8", errors="replace")
    if isinstance(value, np.ndarray) and value.size == 1:
        return _text(value.reshape(-1)[0])
    return printable(value)[:MAX_ATTRIBUTE_CHARS]


class MetavisionHdf5File:
    """A Metavision HDF5 event file opened for reading: ``chunks()`` streams its CD events in file
    order, ``window(t0_us, t1_us)`` decodes only the chunks the 2 ms index points at, ``read()``
    everything, ``triggers()`` the external triggers. ``header`` holds the root attributes (as a
    ``RawHeader``, label "HDF5"), ``width``/``height`` the sensor (``geometry`` overriding it).
    ``engine`` as for EVT 3.0 (``auto``, ``numba``, ``numpy``); ``threads`` decode ECF chunks side
    by side with the compiled engine. Use as a context manager, or call ``close``."""

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        engine: str = "auto",
        geometry: tuple[int, int] | None = None,
        threads: int | None = None,
        batch_events: int = BATCH_EVENTS,
        limits: Limits | None = None,
    ) -> None:
        self.path = Path(path)
        self.engine = resolve(engine)
        self.threads = max(1, threads or default_threads())
        self.limits = limits or Limits.from_env()
        self._file = open_hdf5(self.path)
        try:
            with hdf5_errors(self.path):
                self._events = self._dataset(EVENTS, required=True)
                fields = {str(k): _text(v) for k, v in self._file.attrs.items()}
                self.header = RawHeader(fields=fields, lines=[f"{k} {v}" for k, v in fields.items()], label="HDF5")
                resolved = resolve_geometry(fields, self.path, LABEL, geometry)
                if resolved is None:
                    raise FormatError(self.path, missing_geometry(self.header).replace("HDF5 header", f"{LABEL} root attributes"))
                self.width, self.height, self.header.geometry_source = resolved
                self.header.width, self.header.height = self.width, self.height
                self.count = int(self._events.shape[0])
                self.chunk = self._chunk_events()
                self.ecf = self._filters()
                self.batch_chunks = max(1, int(batch_events) // self.chunk)
        except BaseException:
            self._file.close()
            raise

    def __enter__(self) -> MetavisionHdf5File:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._file.close()

    def _fail(self, message: str) -> FormatError:
        return FormatError(self.path, message)

    def _dataset(self, name: str, required: bool = False) -> h5py.Dataset | None:
        ds = self._file.get(name)
        if ds is None and not required:
            return None
        if not isinstance(ds, h5py.Dataset):
            raise self._fail(f"not a Metavision HDF5 event file (no {name} dataset)")
        names = ds.dtype.names or ()
        absent = [f for f in FIELDS[name] if f not in names]
        if ds.ndim != 1 or absent:
            raise self._fail(f"{name} is not a 1-D table with fields {', '.join(FIELDS[name])}")
        return ds

    def _chunk_events(self) -> int:
        chunks = self._events.chunks
        if chunks is None:  # contiguous: read in batches as if chunked
            return 1 << 14
        if not 0 < chunks[0] <= MAX_CHUNK_EVENTS:
            raise self._fail(f"{EVENTS} has chunks of {chunks[0]} events; at most {MAX_CHUNK_EVENTS} are read")
        return int(chunks[0])

    def _filters(self) -> bool:
        """Whether the events are ECF-compressed (decoded here); FormatError for a filter HDF5 lacks."""
        plist = self._events.id.get_create_plist()
        codes = [plist.get_filter(i)[0] for i in range(plist.get_nfilters())]
        if FILTER_ID in codes:
            if len(codes) > 1:
                raise self._fail(f"{EVENTS} combines the ECF filter with others (ids {codes}); only ECF alone is decoded")
            if self._events.dtype.itemsize != 16:
                raise self._fail(f"{EVENTS} is ECF-compressed but its records are {self._events.dtype.itemsize} bytes, not 16")
            return True
        missing = [c for c in codes if not h5py.h5z.filter_avail(c)]
        if missing:
            raise self._fail(f"{EVENTS} needs HDF5 filter(s) {missing} that are not available (pip install hdf5plugin)")
        return False

    # -- events ---------------------------------------------------------------------------------

    def chunks(self) -> Iterator[EventArray]:
        """The events in batches of whole chunks (about ``batch_events``), in file order."""
        yield from self._batches(0)

    def read(self) -> EventArray:
        return EventArray.concatenate(list(self.chunks()))

    def __len__(self) -> int:
        return self.count

    def _batches(self, first_chunk: int) -> Iterator[EventArray]:
        last_t = np.iinfo(np.int64).min
        total_chunks = -(-self.count // self.chunk)
        for c0 in range(first_chunk, total_chunks, self.batch_chunks):
            c1 = min(total_chunks, c0 + self.batch_chunks)
            with hdf5_errors(self.path):
                events = self._decode_ecf(c0, c1) if self.ecf else self._read_plain(c0, c1)
            if len(events):
                if int(events.t[0]) < last_t:
                    raise self._fail(f"{EVENTS}: time goes back at event {c0 * self.chunk:,} ({int(events.t[0])} µs after {last_t} µs)")
                last_t = int(events.t[-1])
            yield events

    def _read_plain(self, c0: int, c1: int) -> EventArray:
        lo, hi = c0 * self.chunk, min(self.count, c1 * self.chunk)
        rec = self._events.fields(list(FIELDS[EVENTS]))[lo:hi]
        x, y, p, t = (rec[f] for f in FIELDS[EVENTS])
        if len(t):
            bad_p = (p != 0) & (p != 1)
            if bad_p.any():
                raise self._fail(f"{EVENTS}: event {lo + int(np.argmax(bad_p)):,} has polarity {int(p[bad_p][0])}, not 0 or 1")
            out = (x < 0) | (x >= self.width) | (y < 0) | (y >= self.height)
            if out.any():
                k = int(np.argmax(out))
                raise self._fail(f"{EVENTS}: event {lo + k:,} at ({int(x[k])}, {int(y[k])}) lies outside the {self.width}×{self.height} sensor")
            back = np.diff(t) < 0
            if back.any():
                raise self._fail(f"{EVENTS}: time goes back at event {lo + int(np.argmax(back)) + 1:,}")
        return EventArray(x, y, t, 2 * p.astype(np.int8) - 1)

    def _raw_chunks(self, c0: int, c1: int) -> tuple[list[bytes], list[int]]:
        """The stored bytes of chunks c0 … c1-1 and the event count of each one's header, checked."""
        ds_id = self._events.id
        parts, counts = [], []
        for c in range(c0, c1):
            offset = c * self.chunk
            info = ds_id.get_chunk_info_by_coord((offset,))
            if info.byte_offset is None:
                raise self._fail(f"{EVENTS}: chunk {c} (event {offset:,}) is not stored")
            if info.size > self.limits.max_chunk_bytes:
                raise self._fail(f"{EVENTS}: chunk {c} stores {info.size:,} bytes, beyond the {self.limits.max_chunk_bytes:,} allowed")
            mask, data = ds_id.read_direct_chunk((offset,))
            valid = min(self.chunk, self.count - offset)
            if mask & 1:
                raise self._fail(f"{EVENTS}: chunk {c} is stored without its ECF filter, which this reader does not decode")
            if len(data) < 4:
                raise self._fail(f"{EVENTS}: chunk {c} has {len(data)} bytes, too few for an ECF header")
            n = int.from_bytes(data[:4], "little") >> 2
            if n > self.chunk:
                raise self._fail(f"{EVENTS}: chunk {c}'s header counts {n:,} events, more than its chunk of {self.chunk:,} holds")
            if n < valid:
                raise self._fail(f"{EVENTS}: chunk {c}'s header counts {n:,} events where the dataset has {valid:,}")
            parts.append(data)
            counts.append(n)
        return parts, counts

    def _decode_ecf(self, c0: int, c1: int) -> EventArray:
        chunks, counts = self._raw_chunks(c0, c1)
        x, y, t, p, status = decode_batch(chunks, np.array(counts), self.width, self.height, self.engine, self.threads)
        bad = np.flatnonzero(status != OK)
        if len(bad):
            k = int(bad[0])
            raise self._fail(f"{EVENTS}: chunk {c0 + k} (events {(c0 + k) * self.chunk:,}…) {MESSAGES[int(status[k])]}")
        at = np.cumsum(counts)[:-1]
        back = np.flatnonzero(t[at] < t[at - 1])
        if len(back):
            k = int(back[0]) + 1
            raise self._fail(f"{EVENTS}: time goes back from chunk {c0 + k - 1} to chunk {c0 + k}")
        keep = min(len(t), self.count - c0 * self.chunk)  # a last chunk HDF5 padded to full size
        return EventArray(x[:keep], y[:keep], t[:keep], p[:keep])

    # -- time windows ---------------------------------------------------------------------------

    def _table(self, ds: h5py.Dataset, what: str) -> np.ndarray:
        nbytes = ds.shape[0] * ds.dtype.itemsize
        if nbytes > self.limits.max_array_bytes:
            raise self._fail(f"{what} declares {nbytes:,} bytes, beyond the {self.limits.max_array_bytes:,} allowed")
        return ds[()]

    def start_event(self, t0_us: int) -> int:
        """An event position at or before the first event at ``t0_us`` or later, from ``/CD/indexes``
        (0 when the file has none): every event before it is earlier than ``t0_us``."""
        with hdf5_errors(self.path):
            ds = self._dataset(INDEXES)
            if ds is None or ds.shape[0] == 0:
                return 0
            table = self._table(ds, INDEXES)
            try:
                offset = int(_text(ds.attrs["offset"]))
            except (KeyError, ValueError):
                raise self._fail(f"{INDEXES} has no integer 'offset' attribute") from None
        ids, ts = table["id"].astype(np.uint64), table["ts"].astype(np.int64)
        if (ids > self.count).any() or (np.diff(ids.astype(np.int64)) < 0).any() or (np.diff(ts) < 0).any():
            raise self._fail(f"{INDEXES} is not an increasing index into the {self.count:,} events")
        if abs(offset) > 1 << 62 or (len(ts) and int(np.abs(ts).max()) > 1 << 62):
            raise self._fail(f"{INDEXES} holds times beyond ±2⁶² µs")
        k = int(np.searchsorted(ts - offset, t0_us, side="right")) - 1
        return int(ids[k]) if k >= 0 else 0

    def window(self, t0_us: int, t1_us: int) -> EventArray:
        """Events with ``t0_us <= t < t1_us``: decoding starts at the chunk the index points at and
        stops at the first batch that reaches ``t1_us``."""
        t0_us, t1_us = check_window(t0_us, t1_us)
        parts = []
        for events in self._batches(self.start_event(t0_us) // self.chunk):
            parts.append(events[(events.t >= t0_us) & (events.t < t1_us)])
            if len(events) and int(events.t[-1]) >= t1_us:
                break
        return EventArray.concatenate(parts)

    # -- triggers -------------------------------------------------------------------------------

    def triggers(self) -> Triggers:
        """The external trigger edges (channel: ``id``, value: ``p``), empty when the file has none."""
        with hdf5_errors(self.path):
            ds = self._dataset(TRIGGERS)
            table = self._table(ds, TRIGGERS) if ds is not None else None
        if table is None or len(table) == 0:
            return Triggers(np.empty(0, np.int64), np.empty(0, np.uint8), np.empty(0, np.int8))
        p, channel = table["p"].astype(np.int64), table["id"].astype(np.int64)
        if ((p != 0) & (p != 1)).any() or (channel < 0).any() or (channel > 255).any():
            raise self._fail(f"{TRIGGERS} holds a polarity other than 0/1 or a channel outside 0…255")
        if (np.diff(table["t"]) < 0).any():
            raise self._fail(f"{TRIGGERS}: time goes back")
        return Triggers(table["t"], channel, p)
