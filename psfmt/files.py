"""Opening HDF5 files with every failure turned into one clear line."""

from __future__ import annotations

import os
import re
from pathlib import Path

import h5py

from psfmt.errors import FormatError

_TRUNCATED = re.compile(r"truncated file: eof = (\d+).*stored_eof = (\d+)")


def _detail(exc: OSError) -> str:
    """The innermost reason of an HDF5 error: "A (B (C))" → "C"; HDF5's outer words are generic."""
    text = str(exc)
    inner = re.search(r"\(([^()]*)\)+\s*$", text)
    return (inner[1] if inner else text).strip() or type(exc).__name__


def damaged(path: str | os.PathLike[str], exc: OSError) -> FormatError:
    """The FormatError for an HDF5 file that opens but whose data cannot be read (a corrupt chunk)."""
    return FormatError(path, f"damaged HDF5 file ({_detail(exc)})")


def open_hdf5(path: str | os.PathLike[str]) -> h5py.File:
    """Open ``path`` read-only, turning every way it can fail into a one-line FormatError."""
    path = Path(path)
    if not path.exists():
        raise FormatError(path, "no such file")
    if path.is_dir():
        raise FormatError(path, "is a folder, not a capture file")
    try:
        if not h5py.is_hdf5(path):
            raise FormatError(path, "not an HDF5 file")
        return h5py.File(path, "r")
    except PermissionError as exc:
        raise FormatError(path, "permission denied") from exc
    except OSError as exc:
        cut = _TRUNCATED.search(str(exc))
        if cut:
            raise FormatError(path, f"truncated HDF5 file ({cut[1]} of {cut[2]} bytes present)") from exc
        raise damaged(path, exc) from exc
