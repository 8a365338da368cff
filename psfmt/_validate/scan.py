"""Reading datasets block by block in bounded memory, telling a ``Progress`` callback how far it is."""

from __future__ import annotations

from collections.abc import Callable, Iterator

import h5py
import numpy as np

from psfmt._validate.values import element_count

Progress = Callable[[float, str], None]
"""``progress(fraction, message)``: how far a content scan is, 0…1."""

SCAN_CHUNK = 1 << 21
SCAN_BYTES = 1 << 24
"""Bytes of one block a content scan reads (events: ``SCAN_CHUNK`` rows of every column)."""


def blocks(shape: tuple[int, ...], itemsize: int, budget: int = SCAN_BYTES) -> Iterator[tuple[slice, ...]]:
    """Index tuples that cover an array of ``shape`` in blocks of at most ``budget`` bytes (or one
    innermost row), whole trailing axes first."""
    if not shape or element_count(shape) * itemsize <= budget:
        yield tuple(slice(None) for _ in shape)
        return
    inner = element_count(shape[1:]) * itemsize
    if inner <= budget:
        step = max(1, budget // max(1, inner))
        for start in range(0, shape[0], step):
            yield (slice(start, min(start + step, shape[0])),) + tuple(slice(None) for _ in shape[1:])
        return
    for i in range(shape[0]):
        for rest in blocks(shape[1:], itemsize, budget):
            yield (slice(i, i + 1), *rest)


class Scan:
    """Reads datasets block by block and reports the share of all their bytes read so far."""

    def __init__(self, total_bytes: int, progress: Progress | None) -> None:
        self.total = max(1, total_bytes)
        self.done = 0
        self.progress = progress

    def advance(self, nbytes: int, message: str) -> None:
        self.done += nbytes
        if self.progress is not None:
            self.progress(min(1.0, self.done / self.total), message)

    def read(self, ds: h5py.Dataset, label: str) -> Iterator[tuple[tuple[slice, ...], np.ndarray]]:
        for index in blocks(ds.shape, ds.dtype.itemsize):
            block = ds[index]
            self.advance(block.nbytes, label)
            yield index, block
