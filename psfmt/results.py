"""Storing a solver's result inside an existing capture, atomically."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import h5py

from psfmt.atomic import atomic_path
from psfmt.errors import FormatError
from psfmt.files import open_hdf5
from psfmt.model import Result
from psfmt.validate import structure_findings
from psfmt.writer import compression_options, put_result


def write_result(path: str | os.PathLike[str], result: Result) -> None:
    """Add (or replace) ``/results/<result.name>`` in the capture at ``path``.

    The capture is copied beside itself, changed, and renamed back, so an interrupted write leaves
    the original file exactly as it was.
    """
    path = Path(path)
    with open_hdf5(path) as fh:
        errors = [f for f in structure_findings(fh) if f.level == "error"]
    if errors:
        raise FormatError(path, errors[0].text)
    with atomic_path(path) as tmp:
        shutil.copyfile(path, tmp)
        with h5py.File(tmp, "r+") as fh:
            put_result(fh, result, compression_options(1))
