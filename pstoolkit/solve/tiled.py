"""Solving a capture tile by tile on Dask distributed (``solve_tiles``).

The driver cuts each tile's crop from the capture (``tiles.crop_capture``: only that part of the
frames is read, the events are streamed) and sends it to a worker with the solver's name and
options; the worker solves the crop whole and returns its maps; the driver blends them in
(``tiles.Stitcher``) as they arrive and reports tiles done with an ETA. At most two crops per
worker are in flight, so the driver never holds the whole capture. Where the work goes:

- ``scheduler`` given: the Dask scheduler at that address (``tcp://host:8786``); its workers need
  pstoolkit and the solver's plugin installed, but not the capture's file.
- inside a Dask task (a ``pstoolkit batch`` pair): the cluster running it (``worker_client``).
- otherwise a local cluster of ``workers`` processes (one per core when None, at most one per tile)
  — or no cluster at all for a single tile on one worker, which is solved in this process.

Each tile task uses ``threads`` torch threads (local: the cores shared out among the workers; on a
scheduler's workers one, a Dask worker thread being one core).
"""

from __future__ import annotations

import secrets
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import psfmt
from pstoolkit._shared.progress import Progress
from pstoolkit.solve.base import SolverResult
from pstoolkit.solve.cluster import available_cpus
from pstoolkit.solve.tiles import Stitcher, Tile, crop_capture

# Crops submitted per worker before the driver waits for a result.
IN_FLIGHT_PER_WORKER = 2


def solve_tile(solver: str, device: str, options: dict[str, Any], threads: int, crop: psfmt.Capture) -> SolverResult:
    """Worker side: the registered ``solver`` on one crop with ``options`` (which must make it solve
    the crop whole), on ``threads`` torch threads."""
    import numba  # deferred: the driver of a tiled run need not load numba or torch for this
    import torch

    from pstoolkit._shared.allocator import keep_freed_memory
    from pstoolkit.plugin.manager import get_registries

    # a Dask worker's nanny sets MALLOC_TRIM_THRESHOLD_, which pins glibc's mmap threshold at 128 KiB:
    # every array of the solve's steps would come as fresh pages (4× slower tiles, measured)
    keep_freed_memory()
    torch.set_num_threads(max(1, threads))
    # numba's parallel kernels too: threads it keeps beyond the worker's share spin between kernels
    # and took the cores of the other workers (training after the shadow re-detection ran 2.5× slower)
    numba.set_num_threads(max(1, min(threads, numba.config.NUMBA_NUM_THREADS)))
    entry = get_registries().solvers.get(solver)
    return entry.obj(device=device).solve(crop, options)


def eta_text(done: int, total: int, elapsed_s: float) -> str:
    """``tile 3/12, ETA 1:05`` (minutes:seconds at the mean pace so far; no ETA before a tile is done)."""
    if done == 0 or done >= total:
        return f"tile {done}/{total}"
    left = round(elapsed_s / done * (total - done))
    return f"tile {done}/{total}, ETA {left // 60}:{left % 60:02d}"


@contextmanager
def _client(scheduler: str | None, workers: int) -> Iterator[tuple[Any, bool]]:
    """(client, remote): a client of ``scheduler``, of the cluster this code runs in as a task, or
    of a new local cluster of ``workers``; ``remote`` is True when the workers are not this
    machine's own local cluster."""
    from distributed import get_worker, worker_client

    from pstoolkit.solve.cluster import connect, quiet_loop_errors

    try:
        get_worker()
        inside = True
    except ValueError:
        inside = False
    if scheduler is None and inside:
        with worker_client() as client:
            yield client, True
        return
    with quiet_loop_errors():
        client, cluster = connect(scheduler, None if scheduler else workers)
        try:
            yield client, scheduler is not None
        finally:
            client.close()
            if cluster is not None:
                cluster.close()


def solve_tiles(
    capture: psfmt.Capture,
    tiles: list[Tile],
    *,
    solver: str,
    device: str,
    options: dict[str, Any],
    overlap_px: int,
    scheduler: str | None,
    workers: int | None,
    progress: Progress,
) -> SolverResult:
    """The stitched result of the registered ``solver`` run with ``options`` on each tile's crop,
    its diagnostics the tiles' own (``tiles``) and a record of the tiling (``tiling``: tiles, grid,
    overlap, the inner core boundaries ``row_cuts``/``col_cuts``, largest crop, where, torch threads
    per tile, seconds). See the module docstring.

    Parameters
    ----------
    capture
        The whole capture.
    tiles
        The plan (``tiles.plan_tiles``).
    solver, device, options
        The solver's registry name, torch device and full options, set so that it solves a crop whole.
    overlap_px
        The plan's overlap (frame pixels), for the blending weights.
    scheduler
        Address of a Dask scheduler, or None (see the module docstring).
    workers
        Processes of a local cluster (None: one per core, at most one per tile).
    progress
        Called with the share of tiles done and ``tile k/N, ETA m:ss``.
    """
    height, width = psfmt.target_size(capture)
    stitcher = Stitcher(height, width, overlap_px)
    cpus = available_cpus()
    local_workers = max(1, min(len(tiles), workers or cpus))
    started = time.perf_counter()
    progress(0.0, eta_text(0, len(tiles), 0.0))
    where = "this process"
    if len(tiles) == 1 and scheduler is None and local_workers == 1:
        threads = cpus
        stitcher.add(tiles[0], solve_tile(solver, device, options, threads, crop_capture(capture, tiles[0])))
        progress(1.0, eta_text(1, 1, time.perf_counter() - started))
    else:
        from distributed import as_completed

        with _client(scheduler, local_workers) as (client, remote):
            slots = max(1, sum(client.nthreads().values()))
            threads = 1 if remote else max(1, cpus // local_workers)
            where = scheduler or ("the running Dask cluster" if remote else f"a local cluster of {local_workers} workers")
            token = secrets.token_hex(8)
            pending = iter(tiles)
            running: dict[Any, Tile] = {}

            def submit(count: int) -> None:
                for tile in (next(pending, None) for _ in range(count)):
                    if tile is None:
                        return
                    future = client.submit(solve_tile, solver, device, options, threads, crop_capture(capture, tile),
                                           key=f"pstoolkit-tile-{token}-{tile.index}", pure=False, retries=0)
                    running[future] = tile
                    queue.add(future)

            queue = as_completed([], loop=client.loop)
            submit(IN_FLIGHT_PER_WORKER * slots)
            done = 0
            try:
                for future in queue:
                    tile = running.pop(future)
                    stitcher.add(tile, future.result())
                    future.release()
                    done += 1
                    progress(done / len(tiles), eta_text(done, len(tiles), time.perf_counter() - started))
                    submit(1)
            except BaseException:
                client.cancel(list(running))
                raise
    record = {"tiles": len(tiles), "grid": [tiles[0].rows, tiles[0].cols], "overlap_px": overlap_px,
              "row_cuts": sorted({t.top for t in tiles} - {0}), "col_cuts": sorted({t.left for t in tiles} - {0}),
              "largest_crop": list(max((t.crop_shape for t in tiles), key=lambda s: s[0] * s[1])),
              "where": where, "torch_threads_per_tile": threads, "seconds": round(time.perf_counter() - started, 4)}
    return stitcher.result({"tiling": record})
