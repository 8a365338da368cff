"""Two-tier validation of hybrid-capture files: errors (spec violations) and warnings (best practice).

``psfmt._validate.checks.inspect`` is the one set of checks the validator and the reader share, so they agree on every
file. ``structure_findings`` looks at metadata, shapes and storage only (what the reader refuses a
file on): before anything is read, every dataset's declared size is held against what the file
stores and against ``psfmt.Limits``, and links, external storage and filters that would read other
files or inflate without bound are refused. ``content_findings`` then reads every dataset a reader
may read, block by block in bounded memory (sortedness, ranges, finiteness, the index), so a file
that validates also reads. The checks themselves live in ``psfmt._validate``, one module per group
of the file; this module sorts what they find into a report.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

from psfmt import isolate
from psfmt._validate.checks import inspect
from psfmt._validate.findings import Finding
from psfmt._validate.scan import Progress
from psfmt.files import open_hdf5
from psfmt.limits import Limits


@dataclass
class ValidationReport:
    """What ``validate`` found in the file at ``path``: errors and warnings apart, each in the order found."""

    path: Path
    errors: list[Finding] = field(default_factory=list)
    warnings: list[Finding] = field(default_factory=list)

    @property
    def valid(self) -> bool:
        return not self.errors


def check(
    path: Path, *, content: bool, limits: Limits | None = None, progress: Progress | None = None, isolate_check: bool | None = None
) -> list[Finding]:
    """``inspect`` on the file at ``path``, in a child process when ``isolate_check`` (default
    ``psfmt.isolate.enabled()``) says so."""
    if isolate.wanted(isolate_check):
        return isolate.inspect(path, content=content, limits=limits, progress=progress)
    with open_hdf5(path) as f:
        return inspect(f, path, content=content, limits=limits, progress=progress)


def validate(
    path: str | os.PathLike[str],
    *,
    quick: bool = False,
    limits: Limits | None = None,
    progress: Progress | None = None,
    isolate_check: bool | None = None,
) -> ValidationReport:
    """Check a file against the spec: its structure, then (unless ``quick``) every byte of data in
    bounded memory, telling ``progress`` how far the scan is. ``isolate_check`` (default
    ``psfmt.isolate.enabled()``) runs the checks in a child process (see ``psfmt.isolate``). Raises
    FormatError only when the file cannot be read as HDF5 at all, is damaged, or is not a hybrid
    capture of a readable major version."""
    path = Path(path)
    findings = check(path, content=not quick, limits=limits, progress=progress, isolate_check=isolate_check)
    report = ValidationReport(path)
    for finding in findings:
        (report.errors if finding.level == "error" else report.warnings).append(finding)
    return report
