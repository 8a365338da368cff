"""``pstoolkit validate FILE``: check a capture against the spec."""

from __future__ import annotations

from pathlib import Path

import typer

import psfmt
from pstoolkit.cli.app import app


@app.command()
def validate(file: Path = typer.Argument(..., help="A hybrid-capture HDF5 file.")) -> None:
    """Check FILE against spec/hybrid-capture.md. Exit 0 valid (warnings are printed), 1 invalid
    (each error on its own line), 2 the file cannot be read at all."""
    report = psfmt.validate(file)
    for finding in report.errors:
        typer.echo(f"{file}: error: {finding.text}")
    for finding in report.warnings:
        typer.echo(f"{file}: warning: {finding.text}")
    if report.valid:
        typer.echo(f"{file}: valid ({len(report.warnings)} warning(s))")
        return
    raise typer.Exit(1)
