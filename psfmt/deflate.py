"""Shuffle and deflate of HDF5 chunks in worker threads, written whole with direct chunk writes.

HDF5 runs a dataset's filters inside each write call, chunk after chunk on the calling thread. The
filters the format allows for compression (shuffle, then deflate) are plain byte transforms, so
``ChunkCompressor`` applies them itself — numpy for the byte shuffle, a deflate encoder that releases
the GIL for deflate — in a pool of threads, and hands each finished chunk to ``write_direct_chunk``;
meanwhile the writer's caller goes on with its work. At level 1, the format's, the encoder is ISA-L's
where ``isal`` is installed (pstoolkit depends on it; psfmt works without it): a standard zlib
stream, which HDF5's filter and every inflate read (see ``ISAL_ENCODER_LEVEL``; ``psfmt.inflate``
reads with ISA-L too). Otherwise the stored bytes are zlib's, those HDF5's own filters write
(``tests/psfmt/test_deflate.py`` checks both).
"""

from __future__ import annotations

import itertools
import os
import zlib
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import h5py
import numpy as np

try:  # the fast encoder is optional: psfmt must work with numpy and h5py alone
    from isal import isal_zlib
except ImportError:  # pragma: no cover - exercised where isal is absent
    isal_zlib = None

# The deflate level whose chunks ISA-L compresses (see the module docstring), and ISA-L's own level
# for them. A 256² blobs capture (events 8.1 MB, maps 3.2 MB, frames 0.6 MB shuffled), against zlib's
# level 1 (97 ms, 2.80 MB): ISA-L's level 3 takes 38 ms for 2.89 MB, its level 2 13 ms for 2.80 MB,
# 25 ms less CPU per simulated capture. zlib inflates level 2's events in 24 ms against 16 for
# level 3's; ISA-L inflates them in 11 (``psfmt.inflate`` reads event columns that way).
ISAL_LEVEL = 1
ISAL_ENCODER_LEVEL = 2
# Chunks compressing or waiting to be written before a write waits for the oldest: bounds the memory
# held by chunks in flight. Not tied to the thread count, so a file's bytes do not depend on the machine.
PENDING_CHUNKS = 32


def default_threads() -> int:
    """Threads for compressing or inflating chunks: the CPUs, at most 8."""
    return max(1, min(8, os.cpu_count() or 1))


def deflate_chunk(block: np.ndarray, chunk: tuple[int, ...], level: int) -> bytes:
    """One chunk as HDF5's shuffle and deflate filters store it: ``block`` (at most ``chunk`` in each
    axis; an edge chunk is padded with zeros to the full chunk, as HDF5 keeps edge chunks whole),
    its bytes grouped by significance (shuffle), then deflated at ``level`` into a zlib stream
    (by ISA-L at ``ISAL_LEVEL`` where it is installed, else by zlib)."""
    if block.shape != chunk:
        full = np.zeros(chunk, dtype=block.dtype)
        full[tuple(slice(0, n) for n in block.shape)] = block
        block = full
    raw = np.ascontiguousarray(block)
    size = raw.dtype.itemsize
    if size > 1:
        raw = np.ascontiguousarray(raw.reshape(-1).view(np.uint8).reshape(-1, size).T)
    if isal_zlib is not None and level == ISAL_LEVEL:
        return isal_zlib.compress(raw, ISAL_ENCODER_LEVEL)
    return zlib.compress(raw, level)


def shuffle_deflate_level(dataset: h5py.Dataset) -> int | None:
    """The deflate level of a dataset filtered by exactly shuffle then deflate (None otherwise)."""
    plist = dataset.id.get_create_plist()
    filters = [plist.get_filter(i) for i in range(plist.get_nfilters())]
    if [f[0] for f in filters] != [h5py.h5z.FILTER_SHUFFLE, h5py.h5z.FILTER_DEFLATE]:
        return None
    return int(filters[1][2][0])


@dataclass(frozen=True)
class _Layout:
    """What ``ChunkCompressor.write`` needs of a dataset: dtype, chunk shape, deflate level (None:
    written through h5py) and the shape after the first axis where it cannot change (else None)."""

    dtype: np.dtype
    chunks: tuple[int, ...] | None
    level: int | None
    tail: tuple[int, ...] | None

    @classmethod
    def of(cls, dataset: h5py.Dataset) -> _Layout:
        shape, maxshape, chunks = dataset.shape, dataset.maxshape, dataset.chunks
        level = shuffle_deflate_level(dataset) if chunks is not None else None
        return cls(dataset.dtype, chunks, level, shape[1:] if maxshape is None or maxshape[1:] == shape[1:] else None)


class ChunkCompressor:
    """Writes array blocks into chunked, shuffle + deflate datasets, compressing their chunks in
    ``threads`` worker threads (default: the CPUs, at most 8). ``write`` returns once the chunks are
    queued; ``flush`` writes all that are queued. Datasets with other filters are written directly."""

    def __init__(self, threads: int | None = None) -> None:
        self.threads = default_threads() if threads is None else max(1, int(threads))
        self._pool: ThreadPoolExecutor | None = None
        self._pending: deque[tuple[h5py.Dataset, tuple[int, ...], Future[bytes]]] = deque()
        # what each dataset's writes need to know of it, read once: every h5py property is a lookup in
        # the file, slow while it is busy with chunk writes (0.01–0.07 ms each, ~100 a capture)
        self._layouts: dict[h5py.h5d.DatasetID, _Layout] = {}

    def write(self, dataset: h5py.Dataset, data: np.ndarray, start: int = 0, *, copy: bool = True) -> None:
        """Write ``data`` into ``dataset[start : start + len(data)]``, which must exist (resize first),
        ``start`` on a chunk boundary of the first axis and the other axes whole; a last chunk that
        ``data`` fills only in part must be the dataset's last. The caller may reuse its array once
        ``write`` returns, unless it passes ``copy=False``: then it must leave it as it is until
        ``flush`` (its chunks are compressed from it, not from copies)."""
        if dataset.id not in self._layouts:
            self._layouts[dataset.id] = _Layout.of(dataset)
        layout = self._layouts[dataset.id]
        data = np.asarray(data, dtype=layout.dtype)
        if data.ndim == 0:
            dataset[()] = data
            return
        if layout.level is None:
            dataset[start : start + len(data)] = data
            return
        chunk = layout.chunks
        assert chunk is not None
        tail = dataset.shape[1:] if layout.tail is None else layout.tail
        if start % chunk[0] or data.shape[1:] != tail:
            raise ValueError(f"direct chunk write at row {start} of {dataset.name} is not aligned to its chunks {chunk}")
        if self._pool is None:
            self._pool = ThreadPoolExecutor(self.threads, thread_name_prefix="psfmt-deflate")
        grid = [range(0, n, c) for n, c in zip(data.shape, chunk)]
        for corner in itertools.product(*grid):
            block = data[tuple(slice(a, a + c) for a, c in zip(corner, chunk))]
            block = np.array(block) if copy else block
            offset = (start + corner[0], *corner[1:])
            self._pending.append((dataset, offset, self._pool.submit(deflate_chunk, block, chunk, layout.level)))
            # chunks are written at points that depend on counts only, never on timing, so the same data
            # lays out the same file bytes
            while len(self._pending) > PENDING_CHUNKS:
                self._write_oldest()

    def _write_oldest(self) -> None:
        dataset, offset, future = self._pending.popleft()
        dataset.id.write_direct_chunk(offset, future.result())

    def flush(self) -> None:
        """Write every queued chunk (waiting for its compression)."""
        while self._pending:
            self._write_oldest()

    def close(self) -> None:
        """Drop what is queued and stop the threads (after ``flush`` nothing is left to drop)."""
        for _, _, future in self._pending:
            future.cancel()
        self._pending.clear()
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None
