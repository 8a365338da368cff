"""DSEC-style event HDF5: ``/events/{x, y, p, t}``, ``/t_offset`` and ``/ms_to_idx``.

``t`` is in µs relative to ``t_offset``; ``ms_to_idx[i]`` is the first event with ``t >= 1000·i``
(``searchsorted(t, ms·1000, 'left')``), so a time window is sliced without scanning. Any integer
widths are read; polarity 0/1 becomes -1/+1. Events whose x or y does not fit the uint16 of a
capture are dropped and counted (``beyond``), never wrapped round into the sensor. DSEC files are usually zstd-compressed through
``hdf5plugin``: it is imported when installed, and a dataset whose filter is not available is a
one-line FormatError saying what to install.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from psfmt.atomic import atomic_path
from psfmt.errors import FormatError
from psfmt.events import EventArray
from psfmt.files import hdf5_errors, open_hdf5
from psfmt.limits import MAX_SENSOR_SIDE

try:  # registers the zstd/blosc/lz4 filters with HDF5 when present
    import hdf5plugin
except ImportError:  # pragma: no cover - exercised where hdf5plugin is absent
    hdf5plugin = None

COLUMNS = ("x", "y", "p", "t")
DEFAULT_CHUNK_EVENTS = 1 << 20
COMPRESSIONS = ("gzip", "zstd", "none")


def _missing_filters(ds: h5py.Dataset) -> list[str]:
    plist = ds.id.get_create_plist()
    missing = []
    for i in range(plist.get_nfilters()):
        code, _, _, name = plist.get_filter(i)
        if not h5py.h5z.filter_avail(code):
            label = name.decode(errors="replace") if isinstance(name, bytes) else str(name)
            missing.append(f"{label or 'filter'} (id {code})")
    return missing


class DsecFile:
    """A DSEC-style event file opened for reading: ``read``, ``chunks`` or ``window`` (absolute µs)."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.beyond = 0  # events read so far whose x or y exceeds 65535, dropped
        self._file = open_hdf5(self.path)
        try:
            with hdf5_errors(self.path):
                group = self._file.get("events")
                if not isinstance(group, h5py.Group):
                    raise FormatError(self.path, "not a DSEC-style event file (no /events group)")
                absent = [c for c in COLUMNS if not isinstance(group.get(c), h5py.Dataset)]
                if absent:
                    raise FormatError(self.path, f"/events lacks {', '.join(absent)}")
                self._cols = {c: group[c] for c in COLUMNS}
                for c, ds in self._cols.items():
                    if ds.dtype.kind not in "iu" or ds.ndim != 1:
                        raise FormatError(self.path, f"/events/{c} is {ds.dtype} of shape {ds.shape}, expected 1-D integers")
                    missing = _missing_filters(ds)
                    if missing:
                        raise FormatError(
                            self.path,
                            f"/events/{c} needs the HDF5 filter {', '.join(missing)}, which is not installed "
                            "(pip install hdf5plugin)",
                        )
                lengths = {int(ds.shape[0]) for ds in self._cols.values()}
                if len(lengths) != 1:
                    raise FormatError(self.path, "/events columns x, y, p, t differ in length")
                self.count = lengths.pop()
                self.t_offset_us = int(self._file["t_offset"][()]) if "t_offset" in self._file else 0
                self._index = self._file.get("ms_to_idx")
                # DSEC itself stores no geometry; files written here carry it as root attributes
                self.width: int | None = int(self._file.attrs.get("width", 0)) or None
                self.height: int | None = int(self._file.attrs.get("height", 0)) or None
        except BaseException:
            self._file.close()
            raise

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> DsecFile:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _columns(self, lo: int, hi: int, names: tuple[str, ...] = COLUMNS) -> dict[str, np.ndarray]:
        with hdf5_errors(self.path):
            return {c: self._cols[c][lo:hi] for c in names}

    def _slice(self, lo: int, hi: int) -> EventArray:
        cols = self._columns(lo, hi)
        fits = (cols["x"] < MAX_SENSOR_SIDE) & (cols["y"] < MAX_SENSOR_SIDE)
        if not fits.all():
            self.beyond += int(fits.size - np.count_nonzero(fits))
            cols = {c: v[fits] for c, v in cols.items()}
        t = cols["t"].astype(np.int64) + self.t_offset_us
        return EventArray(cols["x"], cols["y"], t, np.where(cols["p"] > 0, 1, -1))

    def extent(self) -> tuple[int, int]:
        """(largest x + 1, largest y + 1) over all events as stored (0, 0 for none), in bounded memory."""
        extent = [0, 0]
        for start in range(0, self.count, DEFAULT_CHUNK_EVENTS):
            cols = self._columns(start, min(start + DEFAULT_CHUNK_EVENTS, self.count), ("x", "y"))
            extent = [max(extent[0], int(cols["x"].max()) + 1), max(extent[1], int(cols["y"].max()) + 1)]
        return extent[0], extent[1]

    def chunks(self, size: int = DEFAULT_CHUNK_EVENTS) -> Iterator[EventArray]:
        for start in range(0, self.count, size):
            yield self._slice(start, min(start + size, self.count))

    def read(self) -> EventArray:
        return self._slice(0, self.count)

    def window(self, t0_us: int, t1_us: int) -> EventArray:
        """Events with ``t0_us <= t < t1_us`` (absolute µs), sliced through ``ms_to_idx`` when present."""
        lo, hi = 0, self.count
        if self._index is not None and len(self._index):
            n = len(self._index)
            i0 = (int(t0_us) - self.t_offset_us) // 1000
            i1 = -(-(int(t1_us) - self.t_offset_us) // 1000)
            lo = int(self._index[min(max(i0, 0), n - 1)]) if i0 > 0 else 0
            hi = int(self._index[i1]) if 0 <= i1 < n else (0 if i1 < 0 else self.count)
        events = self._slice(lo, max(lo, hi))
        return events.window(int(t0_us), int(t1_us))


def ms_to_idx(t_rel_us: np.ndarray) -> np.ndarray:
    """DSEC's millisecond index: for ms = 0 … last, the first event with ``t >= 1000·ms``."""
    last = int(t_rel_us[-1]) // 1000 if len(t_rel_us) else 0
    return np.searchsorted(t_rel_us, 1000 * np.arange(last + 1, dtype=np.int64), side="left").astype(np.uint64)


def _compression(name: str, path: Path) -> dict[str, Any]:
    if name == "gzip":
        return {"compression": "gzip", "compression_opts": 1, "shuffle": True}
    if name == "zstd":
        if hdf5plugin is None:
            raise FormatError(path, "zstd compression needs hdf5plugin (pip install hdf5plugin)")
        return dict(hdf5plugin.Zstd())
    if name == "none":
        return {}
    raise FormatError(path, f"compression {name!r} is not one of {', '.join(COMPRESSIONS)}")


def write_dsec(
    path: str | os.PathLike[str],
    chunks: Iterable[EventArray],
    count: int,
    width: int,
    height: int,
    *,
    t_offset_us: int | None = None,
    compression: str = "gzip",
) -> Path:
    """Write ``count`` sorted events given block by block as a DSEC-style file, atomically.

    ``t_offset`` defaults to the first event's time; ``t`` is stored as u4 when the span fits and
    u8 otherwise; the geometry goes into root attributes ``width``/``height``."""
    path = Path(path)
    options = _compression(compression, path)
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        f.attrs["width"], f.attrs["height"] = int(width), int(height)
        group = f.create_group("events")
        chunk = (max(1, min(count, 1 << 16)),)
        made: dict[str, h5py.Dataset] = {}
        index_parts: list[np.ndarray] = []
        written = 0
        offset = t_offset_us
        done_ms = 0
        last = None
        for block in chunks:
            if len(block) == 0:
                continue
            if offset is None:
                offset = int(block.t[0])
            if not made:
                span = int(block.t[-1]) - offset
                t_type = np.uint32 if count and span < (1 << 31) else np.uint64
                for c, dtype in (("x", np.uint16), ("y", np.uint16), ("p", np.uint8), ("t", t_type)):
                    made[c] = group.create_dataset(c, shape=(count,), dtype=dtype, chunks=chunk, **options)
            t_rel = block.t - offset
            if int(t_rel[0]) < 0 or (last is not None and int(block.t[0]) < last):
                raise ValueError("DSEC export needs sorted events at or after t_offset")
            if made["t"].dtype == np.uint32 and int(t_rel[-1]) >= 1 << 32:
                raise ValueError("events span more than 2^32 µs: give the whole count up front to store u8 times")
            end = written + len(block)
            if end > count:
                raise ValueError(f"more events than the declared count {count}")
            made["x"][written:end] = block.x
            made["y"][written:end] = block.y
            made["p"][written:end] = (block.p > 0).astype(np.uint8)
            made["t"][written:end] = t_rel
            upto = int(t_rel[-1]) // 1000 + 1
            bounds = 1000 * np.arange(done_ms, upto, dtype=np.int64)
            # a bound is final once an event at or after it was seen; the last one waits for the next block
            final = bounds[bounds <= int(t_rel[-1])]
            index_parts.append(written + np.searchsorted(t_rel, final, side="left"))
            done_ms += len(final)
            written = end
            last = int(block.t[-1])
        if written != count:
            raise ValueError(f"got {written} events, {count} declared")
        if not made:
            for c, dtype in (("x", np.uint16), ("y", np.uint16), ("p", np.uint8), ("t", np.uint32)):
                group.create_dataset(c, shape=(0,), dtype=dtype)
        f.create_dataset("t_offset", data=np.int64(offset or 0))
        f.create_dataset("ms_to_idx", data=np.concatenate(index_parts + [np.empty(0, np.int64)]).astype(np.uint64))
    return path
