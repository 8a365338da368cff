"""``pstoolkit eval PATH…``: tables of accuracy, data rate and time over results and captures."""

from __future__ import annotations

from pathlib import Path

import typer

import psfmt
from psfmt.atomic import check_target
from pstoolkit.cli.app import app, echo
from pstoolkit.errors import UserError
from pstoolkit.evaluation.scoring import CSV_COLUMNS, collect, csv_text, json_text, markdown


@app.command("eval")
def eval_command(
    paths: list[Path] = typer.Argument(..., help="Result folders (with result.json), folders of result folders, or captures with stored results."),
    as_json: bool = typer.Option(False, "--json", help="Print JSON: every result and the per-solver averages."),
    as_csv: bool = typer.Option(
        False, "--csv", help=f"Print CSV, one row per result: {', '.join(CSV_COLUMNS)} (shares 0..1)."
    ),
    out: Path | None = typer.Option(None, "-o", "--out", help="Write the output to this file instead of printing it."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="With -o: no line saying what was written."),
) -> None:
    """Compare results: markdown tables with a row per object (capture stem) and a column per solver
    (result name) of the mean angular error in degrees (an unsolved pixel counts 90°), the mean error
    of the solved pixels, the median error, the coverage (share of mask pixels solved), the shares of
    pixels under 11.25°, 22.5° and 30°, data rate and solver seconds, each with an average row over the
    objects that have a value. A result without ground truth, or a metric its result.json predates,
    shows –. Stored results in a capture are scored afresh against its ground truth."""
    if as_json and as_csv:
        raise UserError("--json and --csv: choose one output format")
    records = collect(paths)
    text = json_text(records) if as_json else csv_text(records) if as_csv else markdown(records)
    if out is None:
        echo(text, nl=False)
        return
    if not out.parent.is_dir():
        raise UserError(f"{out}: folder {out.parent} does not exist")
    check_target(out, paths)
    with psfmt.atomic_path(out) as tmp:
        tmp.write_text(text, encoding="utf-8")
    if not quiet and not as_json:  # with --json, stdout holds JSON or nothing: the JSON went to the file
        echo(f"wrote {out}: {len(records)} result(s)")
