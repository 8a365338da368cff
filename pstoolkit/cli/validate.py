"""``pstoolkit validate FILE``: check a capture against the spec."""

from __future__ import annotations

import json
from pathlib import Path

import typer

import psfmt
from psfmt.text import printable
from pstoolkit.cli.app import app, echo, progress_bar


@app.command()
def validate(
    file: Path = typer.Argument(..., help="A hybrid-capture HDF5 file."),
    quick: bool = typer.Option(False, "--quick", help=(
        "Check the structure only (metadata, shapes and sizes against what the file stores); read none of the data."
    )),
    as_json: bool = typer.Option(False, "--json", help="Print the findings as JSON."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar."),
) -> None:
    """Check FILE against spec/hybrid-capture.md: its structure, then every byte of its data, read in
    bounded memory (a progress bar on a terminal; --quick skips the data). A file that validates is
    one `pstoolkit info` and `run` read. Exit 0 valid (warnings are printed), 1 invalid (each error on
    its own line), 2 the file cannot be read at all (one line: missing, not HDF5, damaged …)."""
    report = psfmt.validate(file, quick=quick, progress=progress_bar("validate", quiet or as_json))
    if as_json:
        findings = {
            level: [{"where": f.where, "message": f.message} for f in found]
            for level, found in (("errors", report.errors), ("warnings", report.warnings))
        }
        echo(json.dumps({"file": str(file), "valid": report.valid, "quick": quick, **findings}, indent=2))
    else:
        # a finding names HDF5 paths from the file: one line each, whatever they hold
        for finding in report.errors:
            echo(f"{file}: error: {printable(finding.text)}")
        for finding in report.warnings:
            echo(f"{file}: warning: {printable(finding.text)}")
        if report.valid:
            echo(f"{file}: valid ({len(report.warnings)} warning(s)){' (structure only: --quick)' if quick else ''}")
    if not report.valid:
        raise typer.Exit(1)
