"""The DiLiGenT object-folder layout (Shi et al. 2016; DiLiGenT-Π uses the same): file names and the
light tables, shared by the converters that read such folders, ``pstoolkit export --frames diligent``
that writes them and ``pstoolkit simulate --lights FILE`` that renders under a folder's lights.

    directions, intensities = read_lights(Path("ballPNG/light_directions.txt"))   # (K, 3) each

A folder holds the images named in ``filenames.txt`` (16-bit RGB PNG, stored BGR as OpenCV writes
them), ``light_directions.txt`` and ``light_intensities.txt`` (one ``x y z`` / ``r g b`` line per
image, numbers separated by blanks or commas; the intensities in RGB order), ``mask.png`` (non-zero
inside) and ``Normal_gt.mat`` (variable ``Normal_gt``, float64 (H, W, 3), 0 outside the mask).
Directions and normals are in the camera frame of the capture format: x right, y up, z towards the
camera.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pstoolkit.errors import UserError

FILENAMES = "filenames.txt"
DIRECTIONS = "light_directions.txt"
INTENSITIES = "light_intensities.txt"
MASK = "mask.png"
NORMAL = "Normal_gt.mat"
NORMAL_VARIABLE = "Normal_gt"
MAX_TEXT_BYTES = 16 << 20
"""Largest text file read (a table of 10 000 lights is under 1 MB): a bigger one is refused unread."""


def require_file(path: Path) -> Path:
    """``path``, or UserError naming it when it is not an existing file."""
    if not path.is_file():
        raise UserError(f"{path}: file does not exist")
    return path


def text_lines(path: Path) -> list[str]:
    """The non-blank lines of a UTF-8 text file, stripped; UserError for a missing, oversized or
    binary file."""
    size = require_file(path).stat().st_size
    if size > MAX_TEXT_BYTES:
        raise UserError(f"{path}: {size:,} bytes, more than the {MAX_TEXT_BYTES:,} a light or file table may have")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise UserError(f"{path}: not a text file") from None
    return [line.strip() for line in text.splitlines() if line.strip()]


def read_table(path: Path) -> np.ndarray:
    """A text file of lines with three finite numbers → (K, 3) float64."""
    rows = []
    for number, line in enumerate(text_lines(path), start=1):
        fields = line.replace(",", " ").split()
        try:
            values = [float(f) for f in fields]
        except ValueError:
            raise UserError(f"{path}: line {number}: expected three numbers, got {line!r}") from None
        if len(values) != 3 or not all(np.isfinite(values)):
            raise UserError(f"{path}: line {number}: expected three finite numbers, got {line!r}")
        rows.append(values)
    return np.array(rows, dtype=np.float64).reshape(-1, 3)


def read_directions(path: Path) -> np.ndarray:
    """(K, 3) unit light directions of a ``light_directions.txt``."""
    table = read_table(path)
    norm = np.linalg.norm(table, axis=1, keepdims=True)
    if np.any(norm == 0):
        raise UserError(f"{path}: line {int(np.flatnonzero(norm[:, 0] == 0)[0]) + 1}: a light direction is the zero vector")
    return table / norm


def read_intensities(path: Path) -> np.ndarray:
    """(K, 3) positive RGB light intensities of a ``light_intensities.txt``."""
    table = read_table(path)
    bad = np.flatnonzero(np.any(table <= 0, axis=1))
    if bad.size:
        raise UserError(f"{path}: line {int(bad[0]) + 1}: light intensities must be positive")
    return table


def read_lights(directions_path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(K, 3) unit directions of a light-direction table and (K, 3) RGB intensities from the
    ``light_intensities.txt`` beside it, or 1 when there is none."""
    directions = read_directions(directions_path)
    if len(directions) == 0:
        raise UserError(f"{directions_path}: holds no light direction")
    intensities_path = directions_path.parent / INTENSITIES
    if intensities_path == directions_path or not intensities_path.exists():
        return directions, np.ones_like(directions)
    intensities = read_intensities(intensities_path)
    if len(intensities) != len(directions):
        raise UserError(
            f"{intensities_path}: {len(intensities)} lines, but {directions_path.name} has {len(directions)} lights"
        )
    return directions, intensities
