"""Reading rows of 1-D shuffle + deflate datasets (the event columns) with ISA-L's inflate.

HDF5's deflate filter inflates with zlib, chunk after chunk on the calling thread. Where ``isal`` is
installed, ``ColumnReader`` reads the chunks whole (``read_direct_chunk``) and inflates them with
ISA-L, about twice as fast, undoing the byte shuffle with numpy, in a pool of threads (both release
the GIL). Anything else — other filters, no ``isal``, a chunk that skipped a filter, was never
written or does not inflate to a whole chunk — is read through h5py, so the values, and the errors
of a damaged file, are HDF5's own.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import h5py
import numpy as np

from psfmt.deflate import default_threads, isal_zlib, shuffle_deflate_level

_POOL: list[ThreadPoolExecutor] = []


def _pool() -> ThreadPoolExecutor:
    """The inflating threads (the CPUs, at most 8), started at the first read that needs them."""
    if not _POOL:
        _POOL.append(ThreadPoolExecutor(default_threads(), thread_name_prefix="psfmt-inflate"))
    return _POOL[0]


class ColumnReader:
    """``read(lo, hi)`` = ``dataset[lo:hi]`` of a 1-D dataset, inflated by ISA-L where it can be
    (see the module docstring). The dataset's layout is read once."""

    def __init__(self, dataset: h5py.Dataset) -> None:
        self.dataset = dataset
        chunks = dataset.chunks
        fast = isal_zlib is not None and dataset.ndim == 1 and chunks is not None
        fast = fast and shuffle_deflate_level(dataset) is not None
        self._chunk = int(chunks[0]) if fast and chunks is not None else 0
        self._dtype = dataset.dtype

    def read(self, lo: int, hi: int) -> np.ndarray:
        if self._chunk == 0 or hi <= lo:
            return self.dataset[lo:hi]
        firsts = range(lo - lo % self._chunk, hi, self._chunk)
        # HDF5 reads on this thread (h5py serialises its calls); the chunks inflate in the pool
        raws = [self._raw_chunk(first) for first in firsts]
        if any(raw is None for raw in raws):
            return self.dataset[lo:hi]
        out = np.empty(hi - lo, dtype=self._dtype)

        def place(first: int, raw: bytes) -> bool:
            return self._place(raw, first, lo, hi, out)

        placed = list(_pool().map(place, firsts, raws)) if len(raws) > 1 else [place(firsts[0], raws[0])]
        return out if all(placed) else self.dataset[lo:hi]

    def _raw_chunk(self, first: int) -> bytes | None:
        """The stored bytes of the chunk at row ``first``; None where it skipped a filter or cannot be
        read directly (never written, unreadable): h5py's read then fills or reports it."""
        try:
            mask, raw = self.dataset.id.read_direct_chunk((first,))
        except (OSError, RuntimeError, KeyError, ValueError):
            return None
        return raw if mask == 0 else None

    def _place(self, raw: bytes, first: int, lo: int, hi: int, out: np.ndarray) -> bool:
        """Inflate the chunk at row ``first`` and put its rows within [lo, hi) into ``out``."""
        c, size = self._chunk, self._dtype.itemsize
        try:
            data = isal_zlib.decompress(raw, bufsize=c * size)
        except isal_zlib.error:
            return False
        if len(data) != c * size:
            return False
        a, b = max(lo, first), min(hi, first + c)
        rows = np.frombuffer(data, np.uint8).reshape(size, c).T
        out[a - lo : b - lo].view(np.uint8).reshape(b - a, size)[...] = rows[a - first : b - first]
        return True
