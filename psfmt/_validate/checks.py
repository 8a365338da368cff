"""The one set of checks the reader, the validator and the isolated child share."""

from __future__ import annotations

import os

import h5py

from psfmt._validate.content import content_findings
from psfmt._validate.findings import Finding
from psfmt._validate.scan import Progress
from psfmt._validate.structure import structure_findings
from psfmt.errors import FormatError
from psfmt.files import hdf5_errors
from psfmt.limits import Limits


def inspect(
    f: h5py.File, path: str | os.PathLike[str], *, content: bool, limits: Limits | None = None, progress: Progress | None = None
) -> list[Finding]:
    """The checks the reader and the validator share: structure, then (``content``, and only when the
    structure holds no error) the data. A fatal finding, or anything HDF5 cannot read, raises the
    FormatError that names ``path``."""
    with hdf5_errors(path):
        findings = structure_findings(f, limits)
        fatal = [x for x in findings if x.fatal]
        if fatal:
            raise FormatError(path, fatal[0].text)
        if content and not any(x.level == "error" for x in findings):
            findings += content_findings(f, progress)
    return findings
