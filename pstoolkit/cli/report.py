"""``pstoolkit report DIR… -o REPORT.md``: markdown and HTML report with figures of result folders."""

from __future__ import annotations

from pathlib import Path

import typer

from pstoolkit.cli.app import app, echo
from pstoolkit.evaluation.report import write_report


@app.command()
def report(
    paths: list[Path] = typer.Argument(..., help="Batch folders (of result folders) or result folders written by `pstoolkit run`."),
    out: Path = typer.Option(..., "-o", "--out", help="The markdown report to write (….md); REPORT.html and the PNG figures go beside it."),
) -> None:
    """Write an evaluation report: the tables of `pstoolkit eval` (object × solver: mean angular
    error, of the solved pixels too, median error, coverage, shares under 11.25/22.5/30°, data rate,
    solver time), a plot of the mean angular error against the data rate per solver, each object's
    normal and error maps side by side per solver (unsolved pixels grey), and the pairs a batch failed
    on. Results without ground truth get everything but the errors."""
    files = write_report(paths, out)
    echo(f"wrote {files.markdown}, {files.html.name} and {len(files.figures)} figure(s)")
