"""Light layouts of classic (discrete-light) captures: which instantaneous lights a simulated
capture is rendered under (``pstoolkit simulate --lights ring|grid|FILE``).

- ``ring``: N lights spread evenly over one turn of the simulator's ring light (``RingLight``).
- ``grid``: DiLiGenT's 12×8 light grid (``grid_directions``), 96 lights of intensity 1.
- a path: a DiLiGenT-style ``light_directions.txt`` with the ``light_intensities.txt`` beside it
  (``pstoolkit.io.diligent_layout.read_lights``).

A grid or file layout becomes a ``SampledLight`` through its K directions at times 0, 1, …, K − 1 µs
(``layout_light``), so frame k is rendered at t = k µs under exactly light k.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pstoolkit.errors import UserError
from pstoolkit.io.diligent_layout import read_lights
from pstoolkit.optics.lights import SampledLight

RING, GRID = "ring", "grid"
GRID_COLUMNS, GRID_ROWS = 12, 8
GRID_COLUMN_TAN = (-0.07, -0.21, -0.35, -0.50, -0.65, -0.79, 0.05, 0.19, 0.33, 0.48, 0.62, 0.76)
"""x/z of the LEDs of each grid column (index column, as DiLiGenT numbers them: columns 0–5 run from the
middle to the left, 6–11 from the middle to the right, as seen from the camera)."""
GRID_ROW_TAN0, GRID_ROW_TAN_STEP = -0.48, 0.139
"""y/z of grid row r is ``GRID_ROW_TAN0 + GRID_ROW_TAN_STEP·r``: row 0 at the bottom, row 7 at the top."""


def grid_directions() -> np.ndarray:
    """(96, 3) unit directions of DiLiGenT's light grid, light id = 8·column + row (0-based), the order
    of every DiLiGenT object's ``light_directions.txt``: LEDs on a plane in front of the object at the
    tan-offsets ``GRID_COLUMN_TAN`` (x/z) and ``GRID_ROW_TAN0 + GRID_ROW_TAN_STEP·row`` (y/z). This
    reproduces the calibrated lights of the public rig to within a few degrees (DiLiGenT's own
    directions vary from object to object by about as much)."""
    ids = np.arange(GRID_COLUMNS * GRID_ROWS)
    column, row = ids // GRID_ROWS, ids % GRID_ROWS
    vectors = np.stack(
        [np.asarray(GRID_COLUMN_TAN)[column], GRID_ROW_TAN0 + GRID_ROW_TAN_STEP * row, np.ones(ids.size)], axis=-1
    )
    return vectors / np.linalg.norm(vectors, axis=-1, keepdims=True)


def layout_lights(layout: str) -> tuple[np.ndarray, np.ndarray] | None:
    """(K, 3) unit directions and (K, 3) RGB intensities of a ``grid`` or file layout; None for
    ``ring``, whose lights depend on their count and the ring's elevation. UserError for a file
    that is missing or malformed."""
    if layout == RING:
        return None
    if layout == GRID:
        directions = grid_directions()
        return directions, np.ones_like(directions)
    path = Path(layout)
    if not path.is_file():
        raise UserError(f"--lights {layout!r} is neither ring, grid nor an existing light_directions.txt file")
    return read_lights(path)


def layout_light(directions: np.ndarray, intensities: np.ndarray) -> SampledLight:
    """A non-periodic ``SampledLight`` through ``directions`` (K, 3) with RGB ``intensities`` (K, 3)
    at times 0, 1, …, K − 1 µs."""
    return SampledLight(
        times_us=np.arange(len(directions), dtype=np.float64),
        directions=directions,
        intensities=intensities,
        periodic=False,
    )
