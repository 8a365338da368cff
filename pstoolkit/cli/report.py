"""``pstoolkit report DIR… -o REPORT.md``: markdown and HTML report with figures of result folders."""

from __future__ import annotations

import json
from pathlib import Path

import typer

from pstoolkit.cli.app import app, echo


@app.command()
def report(
    paths: list[Path] = typer.Argument(..., help="Batch folders (of result folders) or result folders written by `pstoolkit run`."),
    out: Path = typer.Option(..., "-o", "--out", help="The markdown report to write (….md); REPORT.html and the PNG figures go beside it."),
    as_json: bool = typer.Option(False, "--json", help="Print the files written as JSON (markdown, html, figures)."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No summary line."),
    ground_truth: list[Path] = typer.Option([], "--ground-truth", help=(
        "A capture whose ground-truth normals head its object's figure (the object is the file stem); repeat for more. "
        "The capture a result.json names is never opened."
    )),
) -> None:
    """Write an evaluation report: the tables of `pstoolkit eval` (object × solver: mean angular
    error, of the solved pixels too, median error, coverage, shares under 11.25/22.5/30°, data rate,
    solver time), a plot of the mean angular error against the data rate per solver, each object's
    normal and error maps side by side per solver (unsolved pixels grey), and the pairs a batch failed
    on. Results without ground truth get everything but the errors."""
    from pstoolkit.evaluation.report import write_report  # deferred: the figures load matplotlib

    files = write_report(paths, out, ground_truth)
    if as_json:
        echo(json.dumps({"markdown": str(files.markdown), "html": str(files.html), "figures": [str(f) for f in files.figures]}, indent=2))
    elif not quiet:
        echo(f"wrote {files.markdown}, {files.html.name} and {len(files.figures)} figure(s)")
