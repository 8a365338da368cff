"""One-line descriptions for the ``repr`` of the data model: shapes, dtypes and counts, never contents.

A capture holds megabytes of arrays; the reprs dataclasses generate print them all (the ``repr`` of a
small demo capture ran to 8,000 characters). These helpers say what an array is (``uint8[6, 64, 64, 3]``)
without reading it, and cut names taken from files to one printable line of bounded length, so a
``repr`` stays one line of a few hundred characters whatever the file holds.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from psfmt.text import printable

NAME_CHARS = 24
"""Longest name (a result's, a material's, a light parameter's) shown before it is cut with ``…``."""
PATH_CHARS = 48
"""Longest path shown: longer ones keep their end (the file name), cut at the start."""
LISTED = 3
"""Names listed before ``+N more``."""


def cut(text: object, limit: int = NAME_CHARS) -> str:
    """``text`` as one printable line of at most ``limit`` characters (its start, then ``…``)."""
    line = printable(text)
    return line if len(line) <= limit else line[: limit - 1] + "…"


def quoted(text: object, limit: int = NAME_CHARS) -> str:
    """``cut(text)`` in single quotes, the way a repr shows a string."""
    return f"'{cut(text, limit)}'"


def path_text(path: Path | str) -> str:
    """A path in quotes, cut at the start when longer than ``PATH_CHARS`` (the file name is what tells)."""
    line = printable(path)
    return f"'{line}'" if len(line) <= PATH_CHARS else f"'…{line[-(PATH_CHARS - 1):]}'"


def names(items: Iterable[object], listed: int = LISTED) -> str:
    """``a, b, c, +2 more``: the first ``listed`` names, each cut, and how many are left out."""
    all_names = list(items)
    shown = ", ".join(cut(name) for name in all_names[:listed])
    rest = len(all_names) - listed
    return f"{shown}, +{rest} more" if rest > 0 else shown


def array_text(array: Any) -> str:
    """``dtype[d0, d1, …]`` of anything with a shape and a dtype (numpy, an HDF5 dataset, a lazy
    stack), read from its metadata only; ``type`` for anything else."""
    shape, dtype = getattr(array, "shape", None), getattr(array, "dtype", None)
    if shape is None or dtype is None:
        return type(array).__name__
    return f"{np.dtype(dtype)}[{', '.join(str(int(d)) for d in shape)}]"


def value_text(value: Any) -> str:
    """A parameter's value: a number or a boolean as itself, a string quoted and cut, an array (or a
    list) by its dtype and shape."""
    if isinstance(value, (bool, np.bool_)):
        return str(bool(value))
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        return f"{float(value):g}"
    if isinstance(value, str):
        return quoted(value)
    if isinstance(value, np.ndarray) and value.ndim == 0:
        return value_text(value.item())
    if isinstance(value, (list, tuple)):
        return f"{type(value).__name__}[{len(value)}]"
    return array_text(value)
