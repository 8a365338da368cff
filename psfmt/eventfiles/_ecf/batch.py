"""Decoding a batch of ECF chunks at once with either engine."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np

from psfmt.eventfiles._ecf.loop import compiled
from psfmt.eventfiles._ecf.vector import decode_vector


def decode_batch(
    chunks: list[bytes], counts: np.ndarray, width: int, height: int, engine: str, threads: int = 1
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """x, y (uint16), t (int64 µs), p (int8 ±1) of the stored ECF ``chunks`` holding ``counts``
    events each (the counts from their headers, checked by the caller), and each chunk's status
    (``psfmt.eventfiles._ecf.chunk``). ``engine`` ``numba`` splits the chunks over ``threads`` threads."""
    sizes = np.array([len(b) for b in chunks], np.int64)
    ends = np.cumsum(sizes)
    starts = ends - sizes
    buf = np.frombuffer(b"".join(chunks), np.uint8)
    counts = np.asarray(counts, np.int64)
    at = np.cumsum(counts) - counts
    total = int(counts.sum())
    x, y = np.empty(total, np.uint16), np.empty(total, np.uint16)
    t, p = np.empty(total, np.int64), np.empty(total, np.int8)
    status = np.zeros(len(counts), np.int64)
    args = (width, height, x, y, t, p)
    if engine != "numba":
        decode_vector(buf, starts, ends, counts, at, *args, status)
        return x, y, t, p, status
    kernel = compiled()
    parts = min(threads, len(counts))
    if parts <= 1:
        kernel(buf, starts, ends, counts, at, *args, status)
        return x, y, t, p, status
    # contiguous runs of chunks of about equal bytes, one per thread (the kernel releases the GIL)
    cuts = np.searchsorted(ends, np.linspace(0, int(ends[-1]), parts + 1)[1:-1])
    bounds = [0, *cuts.tolist(), len(counts)]
    with ThreadPoolExecutor(parts) as pool:
        jobs = [pool.submit(kernel, buf, starts[a:b], ends[a:b], counts[a:b], at[a:b], *args, status[a:b]) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]
        for job in jobs:
            job.result()
    return x, y, t, p, status
