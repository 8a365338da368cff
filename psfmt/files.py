"""Opening HDF5 files with every failure turned into one clear line."""

from __future__ import annotations

import os
from pathlib import Path

import h5py

from psfmt.errors import FormatError


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
        reason = str(exc).split("(")[0].strip().rstrip(",") or type(exc).__name__
        raise FormatError(path, f"truncated or damaged HDF5 file ({reason})") from exc
