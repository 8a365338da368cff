"""When and how ``dualres`` cuts a capture into tiles (``plan``), from a model of its peak memory.

The solve's memory grows with the frame pixels it holds at once: a process solving the whole capture
peaks at ``UNTILED_BASE_BYTES`` + ``BYTES_PER_PIXEL`` per frame pixel (frames, the shared time grid's
lit shares, the field and Adam's moments, the event pairs, the re-detection's height solve and dark
map); a Dask worker process with torch and numba loaded holds ``WORKER_BASE_BYTES`` before a tile,
which then adds ``TILE_BYTES_PER_PIXEL`` per frame pixel of its crop; the driver of a tiled run holds
its own process with torch, the local cluster's scheduler and nannies (``DRIVER_BYTES``) and
``STITCH_BYTES_PER_PIXEL`` per frame pixel of the whole frame for the blended maps. The constants are measured with
``benchmarks/dualres_scale.py`` (docs/dualres-tuning.md, "Tiles").
"""

from __future__ import annotations

import math
from typing import Any

from pstoolkit import UserError
from pstoolkit.solve.cluster import available_cpus, available_memory_bytes
from pstoolkit.solve.tiles import ALIGN_PX, Tile, plan_tiles

WORKER_BASE_BYTES = 0.65e9
# a tile worker's bytes per pixel of its crop: the line of the tiled runs it was fitted to, above the
# whole solve's BYTES_PER_PIXEL, so a tile plan errs on the side of memory (benchmarks/NOTES.md)
TILE_BYTES_PER_PIXEL = 3.8e3
# a plain process with torch loaded, solving the whole capture itself: a line above the peaks of
# 256², 512² and 1024² (0.67, 1.16, 2.41 GB)
UNTILED_BASE_BYTES = 0.72e9
BYTES_PER_PIXEL = 1.72e3
DRIVER_BYTES = 1.1e9
STITCH_BYTES_PER_PIXEL = 80.0
# The smallest core a memory budget may ask for: below it the overlaps cost more than the tiles.
MIN_TILE_PX = 96
GB = 1e9


def budget_bytes(memory_gb: float) -> float:
    """``memory_gb`` in bytes; 0 = half the memory this process may use (``available_memory_bytes``)."""
    return memory_gb * GB if memory_gb > 0 else available_memory_bytes() / 2


def whole_bytes(pixels: int) -> float:
    """Predicted peak of solving ``pixels`` frame pixels in one piece, in this process."""
    return UNTILED_BASE_BYTES + BYTES_PER_PIXEL * pixels


def tile_px_for(budget: float, pixels: int, workers: int, overlap_px: int, *, local: bool) -> int:
    """The largest core side (a multiple of ``ALIGN_PX``) whose crops fit ``budget`` bytes: shared by
    the driver and ``workers`` workers when ``local``, else the budget of one worker. UserError when
    it is below ``MIN_TILE_PX``."""
    per_worker = (budget - DRIVER_BYTES - STITCH_BYTES_PER_PIXEL * pixels) / workers if local else budget
    crop_pixels = (per_worker - WORKER_BASE_BYTES) / TILE_BYTES_PER_PIXEL
    side = math.isqrt(max(0, int(crop_pixels))) - 2 * overlap_px
    tile_px = side // ALIGN_PX * ALIGN_PX
    if tile_px < MIN_TILE_PX:
        where = f"{workers} local workers and the driver" if local else "one worker"
        raise UserError(
            f"dualres: memory_gb = {budget / GB:.2f} leaves room for tiles of only {max(tile_px, 0)} px a side "
            f"({where}; at least {MIN_TILE_PX} px with overlap_px = {overlap_px}): give more memory, fewer --workers or less overlap"
        )
    return tile_px


def plan(shape: tuple[int, int], options: dict[str, Any], *, scheduler: str | None, workers: int | None) -> list[Tile] | None:
    """The tiles to solve a frame of ``shape`` (H, W) in, or None to solve it whole in this process:
    ``tile_px`` −1 never tiles; a positive ``tile_px`` gives tiles of that size; 0 tiles only when the
    predicted peak of the whole solve exceeds ``memory_gb`` (or a ``scheduler`` is given), with the
    largest tiles the budget allows. A plan of one tile with no scheduler is None too."""
    tile_px = options["tile_px"]
    if tile_px == -1:
        return None
    height, width = shape
    pixels = height * width
    if tile_px == 0:
        budget = budget_bytes(options["memory_gb"])
        if scheduler is None and whole_bytes(pixels) <= budget:
            return None
        local = scheduler is None
        count = workers or available_cpus() if local else 1
        tile_px = tile_px_for(budget, pixels, count, options["overlap_px"], local=local)
    tiles = plan_tiles(height, width, tile_px=tile_px, overlap_px=options["overlap_px"])
    return None if len(tiles) == 1 and scheduler is None else tiles
