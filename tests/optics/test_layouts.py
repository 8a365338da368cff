"""Light layouts of classic captures: DiLiGenT's grid (ids, axes, the semi-real converter's boundary
loop walking its edge) and light tables read from DiLiGenT-style files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pstoolkit.errors import UserError
from pstoolkit.optics.layouts import GRID_COLUMN_TAN, GRID_COLUMNS, GRID_ROWS, grid_directions, layout_light, layout_lights
from pstoolkit_diligent.semireal import BOUNDARY_LOOP


def grid_places() -> tuple[np.ndarray, np.ndarray]:
    """(96,) physical column (0 = leftmost, as seen from the camera) and row (0 = lowest) of each grid
    light, read off its direction."""
    d = grid_directions()
    x_tan, y_tan = d[:, 0] / d[:, 2], d[:, 1] / d[:, 2]
    columns = np.unique(np.round(x_tan, 9))
    rows = np.unique(np.round(y_tan, 9))
    assert (len(columns), len(rows)) == (GRID_COLUMNS, GRID_ROWS)
    return np.searchsorted(columns, np.round(x_tan, 9)), np.searchsorted(rows, np.round(y_tan, 9))


def test_grid_ids_are_column_major_with_diligents_axes() -> None:
    d = grid_directions()
    assert d.shape == (96, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-15)
    assert np.all(d[:, 2] > 0)  # every LED in front of the object, towards the camera
    column, row = np.arange(96) // 8, np.arange(96) % 8
    np.testing.assert_allclose(d[:, 0] / d[:, 2], np.asarray(GRID_COLUMN_TAN)[column], atol=1e-12)
    np.testing.assert_allclose(d[:, 1] / d[:, 2], -0.48 + 0.139 * row, atol=1e-12)
    # id 0 (column 0, row 0) sits just left of the middle at the bottom, id 95 at the top right corner
    assert d[0, 0] < 0 and d[0, 1] < 0 and d[48, 0] > 0
    tan = d[:, :2] / d[:, 2:]
    np.testing.assert_allclose(tan[95], tan.max(axis=0), atol=1e-12)
    # the grid spans about ±38° horizontally and from −26° to +26° vertically
    assert 37 < np.degrees(np.arctan(max(GRID_COLUMN_TAN))) < 38
    assert -27 < np.degrees(np.arctan(d[:, 1] / d[:, 2])).min() < -25


def test_the_semi_real_boundary_loop_walks_the_edge_of_the_grid() -> None:
    place_column, place_row = grid_places()
    loop = np.asarray(BOUNDARY_LOOP)
    c, r = place_column[loop], place_row[loop]
    # all 36 edge cells, once each
    on_edge = (c == 0) | (c == GRID_COLUMNS - 1) | (r == 0) | (r == GRID_ROWS - 1)
    assert on_edge.all() and len(set(zip(c, r))) == 36 == 2 * (GRID_COLUMNS + GRID_ROWS) - 4
    # each step (and the closing one) goes to a neighbouring cell
    steps = np.abs(np.roll(c, -1) - c) + np.abs(np.roll(r, -1) - r)
    assert np.all(steps == 1)
    # one turn, counter-clockwise in the image plane (x right, y up): positive signed area
    area = 0.5 * np.sum(c * np.roll(r, -1) - np.roll(c, -1) * r)
    assert area == (GRID_COLUMNS - 1) * (GRID_ROWS - 1)
    # it starts at the right edge, bottom to top (ids 88…95 are column 11)
    assert list(c[:8]) == [GRID_COLUMNS - 1] * 8 and list(r[:8]) == list(range(8))


def test_a_light_table_file_with_its_intensities(tmp_path: Path) -> None:
    directions = np.array([[0.1, 0.2, 1.0], [-0.3, 0.0, 2.0], [0.0, -0.5, 1.0]])
    (tmp_path / "light_directions.txt").write_text("0.1 0.2 1.0\n-0.3, 0, 2\n\n0 -0.5 1\n")
    np.savetxt(tmp_path / "light_intensities.txt", [[1.0, 2.0, 3.0], [0.5, 0.5, 0.5], [2.0, 1.0, 0.25]])
    got, intensities = layout_lights(str(tmp_path / "light_directions.txt"))
    np.testing.assert_allclose(got, directions / np.linalg.norm(directions, axis=1, keepdims=True), atol=1e-15)
    np.testing.assert_allclose(intensities, [[1.0, 2.0, 3.0], [0.5, 0.5, 0.5], [2.0, 1.0, 0.25]])
    light = layout_light(got, intensities)
    direction, intensity = light.evaluate(np.arange(3.0))
    np.testing.assert_allclose(direction, got, atol=1e-15)
    np.testing.assert_allclose(intensity, intensities)
    (tmp_path / "light_intensities.txt").unlink()
    assert np.array_equal(layout_lights(str(tmp_path / "light_directions.txt"))[1], np.ones((3, 3)))
    assert layout_lights("ring") is None


@pytest.mark.parametrize(
    ("directions", "intensities", "message"),
    [
        ("0 0 1\n1 2\n", None, "light_directions.txt: line 2: expected three finite numbers, got '1 2'"),
        ("0 0 1\n0 0 0\n", None, "light_directions.txt: line 2: a light direction is the zero vector"),
        ("0 0 1\n0 1 1\n", "1 1 1\n", "light_intensities.txt: 1 lines, but light_directions.txt has 2 lights"),
        ("0 0 1\n", "1 -1 1\n", "light_intensities.txt: line 1: light intensities must be positive"),
        ("\n", None, "light_directions.txt: holds no light direction"),
        (b"\xff\xfe0 0 1\n", None, "light_directions.txt: not a text file"),
    ],
)
def test_bad_light_tables_are_one_line_errors(tmp_path: Path, directions: str | bytes, intensities: str | None, message: str) -> None:
    path = tmp_path / "light_directions.txt"
    path.write_bytes(directions if isinstance(directions, bytes) else directions.encode())
    if intensities is not None:
        (tmp_path / "light_intensities.txt").write_text(intensities)
    with pytest.raises(UserError, match=message.replace("(", r"\(").replace(")", r"\)")):
        layout_lights(str(path))


def test_an_unknown_layout_that_is_no_file_is_named(tmp_path: Path) -> None:
    with pytest.raises(UserError, match="--lights 'gird' is neither ring, grid nor an existing light_directions.txt file"):
        layout_lights("gird")
