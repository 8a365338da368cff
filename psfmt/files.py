"""Opening HDF5 files with every failure turned into one clear line.

h5py reports a damaged file through whatever exception the failing call raises (``OSError``,
``RuntimeError``, ``KeyError``, ``ValueError`` …); ``hdf5_errors`` turns each into the one
``FormatError`` "damaged HDF5 file (…)", so no reader or validator lets a traceback through.
"""

from __future__ import annotations

import errno
import os
import re
import stat
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import h5py

from psfmt.errors import FormatError

_TRUNCATED = re.compile(r"truncated file: eof = (\d+).*stored_eof = (\d+)")
PLAUSIBLE_FILE_BYTES = 1 << 50
"""A superblock recording a larger end of file (1 PiB) is damaged, not the file truncated."""
HDF5_ERRORS = (OSError, RuntimeError, KeyError, ValueError, TypeError, OverflowError)
"""What h5py raises on a damaged file (RuntimeError covers a RecursionError in nested JSON too)."""


def _detail(exc: BaseException) -> str:
    """The innermost reason of an HDF5 error: "A (B (C))" → "C"; HDF5's outer words are generic."""
    text = exc.args[0] if isinstance(exc, KeyError) and exc.args and isinstance(exc.args[0], str) else str(exc)
    text = text.strip()
    while text.endswith(")"):
        depth, start = 0, -1
        for i in range(len(text) - 1, -1, -1):
            depth += {")": 1, "(": -1}.get(text[i], 0)
            if depth == 0:
                start = i
                break
        if start <= 0:  # unbalanced, or nothing outside the parentheses
            break
        text = text[start + 1 : -1].strip()
    return text or type(exc).__name__


def damaged(path: str | os.PathLike[str], exc: BaseException) -> FormatError:
    """The FormatError for an HDF5 file that opens but whose data cannot be read (a corrupt chunk)."""
    return FormatError(path, f"damaged HDF5 file ({_detail(exc)})")


@contextmanager
def hdf5_errors(path: str | os.PathLike[str]) -> Iterator[None]:
    """Inside the block, any error h5py raises becomes ``damaged(path, …)``; a FormatError passes."""
    try:
        yield
    except FormatError:
        raise
    except HDF5_ERRORS as exc:
        raise damaged(path, exc) from exc


def require_open(obj: h5py.HLObject, path: str | os.PathLike[str]) -> None:
    """A FormatError when the file behind ``obj`` was closed (lazy parts are read while it is open)."""
    if not obj.id.valid:
        raise FormatError(path, "the capture is closed: read its lazy parts while it is open, or load it whole with psfmt.load")


def check_file(path: str | os.PathLike[str], kind: str = "capture file") -> Path:
    """``path`` if it is a file that can be opened; else a FormatError saying why: no such file (or a
    link to none), a loop of symbolic links, a folder, something other than a file, permission denied."""
    path = Path(path)
    try:
        mode = path.stat().st_mode
    except FileNotFoundError:
        raise FormatError(path, "is a symbolic link to a missing file" if path.is_symlink() else "no such file") from None
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise FormatError(path, "is a loop of symbolic links") from None
        if exc.errno == errno.EACCES:
            raise FormatError(path, "permission denied") from None
        raise FormatError(path, f"cannot be read ({exc.strerror or exc})") from None
    if stat.S_ISDIR(mode):
        raise FormatError(path, f"is a folder, not a {kind}")
    if not stat.S_ISREG(mode):
        raise FormatError(path, f"is not a regular file (a device, pipe or socket), not a {kind}")
    return path


def open_hdf5(path: str | os.PathLike[str]) -> h5py.File:
    """Open ``path`` read-only, turning every way it can fail into a one-line FormatError."""
    path = check_file(path)
    try:
        if not h5py.is_hdf5(path):
            raise FormatError(path, "not an HDF5 file")
        return h5py.File(path, "r")
    except FormatError:
        raise
    except PermissionError as exc:
        raise FormatError(path, "permission denied") from exc
    except OSError as exc:
        cut = _TRUNCATED.search(str(exc))
        if cut and int(cut[2]) <= PLAUSIBLE_FILE_BYTES:
            raise FormatError(path, f"truncated HDF5 file ({cut[1]} of {cut[2]} bytes present)") from exc
        if cut:
            raise FormatError(path, f"damaged HDF5 file (its superblock records an end at byte {cut[2]}; the file has {cut[1]} bytes)") from exc
        raise damaged(path, exc) from exc
    except HDF5_ERRORS as exc:
        raise damaged(path, exc) from exc
