"""Cast shadows for the ring-light engine, a block of time at a time: the visibility rows of the
renderer's shadow grid around the block (``sweep_rows``), and per frame pixel the grid intervals in
which a cast shadow falls on it while it is lit (``lit_shadow``), so that a pixel reads the table and
steps short only around those (``shadow_room``)."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numba
import numpy as np
from numba.cpython.unsafe.numbers import trailing_zeros

from pstoolkit.sim.ring_kernels.inputs import NX, NY, NZ, FrameInputs, RingParams, ShadowGrid, ShadowTable
from pstoolkit.sim.ring_kernels.tuning import PIXELS_PER_TASK, SHADOW_TILE, TABLE_ROWS


@dataclass(frozen=True)
class CastShadows:
    """The renderer's cast shadows as the table reads them (``pstoolkit.sim.ring_engine.cast_shadows``):
    whether the scene has any (``shadows``), the step of its shadow grid ``step_us``, its
    ``frame_openness`` of grid keys (``Renderer.frame_openness``) and the frame's ``pixels`` (H·W)."""

    shadows: bool
    step_us: float | None
    frame_openness: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
    pixels: int


@numba.njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def lit_shadow(
    values: np.ndarray, index: np.ndarray, index_t: np.ndarray, sin_e: float, openness: np.ndarray,
    column_major: np.ndarray, light_rows: np.ndarray,
) -> np.ndarray:  # pragma: no cover - compiled
    """(H·W,) uint64: bit i set where a cast shadow falls on the frame pixel while it is lit between
    grid times i and i + 1 of the table (V < 1 at one of them, next to a grid time where n·l > 0: a
    shadow inside the attached shadow changes nothing, as on the far side of a sphere); at most
    ``TABLE_ROWS`` grid times. ``light_rows`` (3, rows): the light's x and y at each grid time of
    the table and how far n·l may exceed its values at the grid times around (n·l is a sinusoid in
    the azimuth). ``values`` are the masked pixels' ``FrameConstants``, ``index`` and ``index_t``
    their flat positions row- and column-major, the columns of ``openness``'s rows without and with
    ``column_major`` (``Renderer.frame_openness``)."""
    rows, span = openness.shape
    if rows > TABLE_ROWS:
        raise ValueError("lit_shadow: a shadow table of more than TABLE_ROWS grid times")
    pixels = index.size
    # bit r: V < 1 at grid time r, by column of the row-major rows and of the column-major ones; in
    # tiles of columns whose bits stay in the L1 cache while the table's rows stream by (SIMD)
    below = np.empty(span, np.uint64)
    below_t = np.empty(span, np.uint64)
    for tile in numba.prange((span + SHADOW_TILE - 1) // SHADOW_TILE):
        start, stop = tile * SHADOW_TILE, min((tile + 1) * SHADOW_TILE, span)
        bits, bits_t = below[start:stop], below_t[start:stop]
        bits[:] = 0
        bits_t[:] = 0
        for row in range(rows):
            line, target = openness[row, start:stop], bits_t if column_major[row] else bits
            bit = np.uint64(1) << np.uint64(row)
            for j in range(stop - start):
                target[j] |= bit if line[j] < 1.0 else np.uint64(0)
    out = np.zeros(span, np.uint64)
    light_x, light_y, slack = light_rows[0], light_rows[1], light_rows[2]
    intervals = (np.uint64(1) << np.uint64(rows - 1)) - np.uint64(1)
    # most pixels are never shadowed in a block and are done with at the first test
    for run in numba.prange((pixels + PIXELS_PER_TASK - 1) // PIXELS_PER_TASK):
        for f in range(run * PIXELS_PER_TASK, min((run + 1) * PIXELS_PER_TASK, pixels)):
            shadow = below[index[f]] | below_t[index_t[f]]
            if shadow == 0:
                continue
            lit = np.uint64(0)
            for row in range(rows):
                nl = values[f, NX] * light_x[row] + values[f, NY] * light_y[row] + values[f, NZ] * sin_e
                lit |= (np.uint64(1) << np.uint64(row)) if nl > -slack[row] else np.uint64(0)
            # the light first: on a sphere's far side the whole table is below one but nothing is lit
            near = shadow & (lit | (lit << np.uint64(1)) | (lit >> np.uint64(1)))
            out[index[f]] = (near | (near >> np.uint64(1))) & intervals
    return out


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def shadow_room(
    t_us: float, shadows: np.uint64, table: ShadowTable, grid_dt: float, max_dt: float,
) -> float:  # pragma: no cover - compiled
    """Longest step from ``t_us`` of a pixel whose frame pixels are shadowed while lit in the grid
    intervals ``shadows`` (bits, see ``lit_shadow``) of ``table``: one grid interval inside such an interval or
    close to one, else up to the next one (no sweep is stepped over), at most ``max_dt``."""
    if shadows == 0:
        return max_dt
    i = min(max(int(math.floor(t_us / table.grid_step_us - table.grid_first)), 0), 63)
    rest = shadows >> np.uint64(i)
    if rest & np.uint64(1):
        return grid_dt
    rest >>= np.uint64(1)
    if rest == 0:
        return max_dt
    j = i + 1 + int(trailing_zeros(rest))
    return min(max((table.grid_first + j) * table.grid_step_us - t_us, grid_dt), max_dt)


def sweep_rows(cast: CastShadows, ta: float, tb: float) -> tuple[np.ndarray, np.ndarray, ShadowGrid]:
    """Unclipped visibility (``pstoolkit.optics.shadow_sweep._openness`` of the shadow margins) of the frame pixels at the
    grid times around [ta, tb]: (N, H·W) float32 rows for keys first, first + 1, … (the renderer's
    sweep buffer, valid until its next sweep), which of them are column-major (N,) (see
    ``Renderer.frame_openness``), and the grid. Without cast shadows two rows of ones (V = 1
    everywhere)."""
    if not cast.shadows:
        return (np.ones((2, cast.pixels), dtype=np.float32), np.zeros(2, np.bool_), ShadowGrid(1.0, 0.0))
    step = float(cast.step_us)  # type: ignore[arg-type]
    first = math.floor(ta / step)
    openness, column_major = cast.frame_openness(np.arange(first, math.floor(tb / step) + 2))
    return openness, column_major, ShadowGrid(step, float(first))


def grid_light(ring: RingParams, rows: int, grid: ShadowGrid) -> np.ndarray:
    """For ``lit_shadow``, (3, rows): per grid time of a shadow table, the light's x and y and how far
    n·l may exceed the larger of its values at neighbouring grid times (``cos e·(ω·step)²``)."""
    phi = ring.phase_rad + ring.omega_rad_per_us * ((grid.first + np.arange(rows)) * grid.step_us - ring.t0_us)
    slack = np.full(rows, ring.cos_e * (ring.omega_rad_per_us * grid.step_us) ** 2)
    return np.stack([ring.cos_e * np.cos(phi), ring.cos_e * np.sin(phi), slack])


def block_table(cast: CastShadows, ta: float, tb: float, frame: FrameInputs, ring: RingParams) -> ShadowTable:
    """The shadow table of the block [ta, tb]: ``sweep_rows`` and, with cast shadows, the frame pixels'
    ``lit_shadow`` bits (without, none: no pixel is shadowed while lit)."""
    openness, column_major, grid = sweep_rows(cast, ta, tb)
    if not cast.shadows:
        return ShadowTable(openness, column_major, *grid, np.zeros(openness.shape[1], np.uint64))
    reach = lit_shadow(frame.values, frame.index, frame.index_t, ring.sin_e, openness, column_major,
                       grid_light(ring, openness.shape[0], grid))
    return ShadowTable(openness, column_major, *grid, reach)
