"""Storing a solver's result inside an existing capture, atomically."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import h5py

from psfmt.atomic import atomic_path, locked
from psfmt.errors import FormatError
from psfmt.model import Result
from psfmt.storing import compression_options, put_result
from psfmt.validate import check


def write_result(path: str | os.PathLike[str], result: Result) -> None:
    """Add (or replace) ``/results/<result.name>`` in the capture at ``path``.

    The capture is copied beside itself, changed, and renamed back, so an interrupted write leaves
    the original file exactly as it was. The whole update holds the capture's lock
    (``psfmt.atomic.locked``), so processes storing results in one capture at once each copy the
    file as the one before them left it: no result is lost.
    """
    path = Path(path)
    with locked(path):
        errors = [f for f in check(path, content=False) if f.level == "error"]
        if errors:
            raise FormatError(path, errors[0].text)
        with atomic_path(path) as tmp:
            shutil.copyfile(path, tmp)
            with h5py.File(tmp, "r+") as fh:
                put_result(fh, result, compression_options(1))
