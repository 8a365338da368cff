"""``pstoolkit batch CAPTURE… --solver NAME … -o DIR``: every (capture, solver) pair on Dask distributed."""

from __future__ import annotations

import json
from pathlib import Path

import typer

from pstoolkit.cli.app import app, echo, progress_bar
from pstoolkit.cli.config import batch_assignments, config_option, file_value
from pstoolkit.errors import UserError
from pstoolkit.solve.base import DEVICES


@app.command()
def batch(
    ctx: typer.Context,
    captures: list[Path] = typer.Argument(None, help="Capture files, or folders whose *.h5 files are captures (or captures in --config FILE)."),
    solvers: list[str] = typer.Option(..., "--solver", help="A registered solver; repeat for more."),
    out: Path = typer.Option(..., "-o", "--out", help="Output folder: one result folder <object>-<solver> per pair, and batch.json."),
    assignments: list[str] = typer.Option([], "--set", metavar="[SOLVER.]KEY=VALUE", help=(
        "An option of every solver that has it, or with SOLVER. of that solver only; repeat for more."
    )),
    scheduler: str | None = typer.Option(None, "--scheduler", help="Address of a running Dask scheduler (tcp://host:8786); default: a local cluster."),
    workers: int | None = typer.Option(None, "--workers", help="Worker processes of the local cluster (default: one per CPU core; at most four per core)."),
    device: str = typer.Option("auto", "--device", help="auto (CUDA when a worker has it), cpu or cuda."),
    error_max: float = typer.Option(30.0, "--error-max", help="Angular error (degrees, above 0 and at most 180) at the top of error.png's colour scale."),
    as_json: bool = typer.Option(False, "--json", help=(
        "Print the outcome as JSON (pairs done, skipped and failed, each failure, the log file) and no progress."
    )),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar (failed pairs are still reported on stderr)."),
    config: Path | None = config_option("batch"),
) -> None:
    """Run every solver on every capture, one Dask task per (capture, solver) pair. Each pair writes
    the folder `pstoolkit run` would (normal maps, error map, result.json) into DIR/<object>-<solver>,
    atomically; a rerun skips the pairs whose folder is complete, so an interrupted batch resumes. A
    failing pair is reported and recorded in DIR/batch.json and the others go on. Exit code 0 when
    every pair succeeded, 1 when any failed, 2 on bad input. With --config FILE, the settings come
    from a TOML file (docs/config.md). Result folders record the options as resolved."""
    # deferred: a batch loads OpenCV (result maps) and, when it computes, dask; `pstoolkit --help` needs neither
    from pstoolkit.solve.batch import (
        check_output_folder,
        expand_captures,
        is_complete,
        plan,
        run_batch,
        solver_options,
        status_counts,
        write_log,
    )
    from pstoolkit.solve.cluster import connect, quiet_loop_errors
    from pstoolkit.solve.results import check_error_max

    captures = list(captures or file_value(ctx, "captures") or [])
    if not captures:
        raise UserError("give the CAPTURE files or folders to run on (or captures in --config FILE)")
    check_error_max(error_max, "--error-max")
    if device not in DEVICES:
        raise UserError(f"--device {device!r}: expected one of {', '.join(DEVICES)}")
    if out.exists() and not out.is_dir():
        raise UserError(f"{out}: exists and is not a folder")
    check_output_folder(out)
    options = solver_options(solvers, batch_assignments(ctx, solvers, assignments))
    pairs = plan(expand_captures(captures), options, out, device=device, error_max_deg=error_max)
    progress = progress_bar("batch", quiet or as_json)
    if all(is_complete(pair) for pair in pairs):
        outcomes = run_batch(pairs, None, progress)  # nothing to compute: no cluster to start
    else:
        with quiet_loop_errors():
            client, cluster = connect(scheduler, workers)
            try:
                outcomes = run_batch(pairs, client, progress)
            finally:
                client.close()
                if cluster is not None:
                    cluster.close()
    log = write_log(out, outcomes)
    failed = [o for o in outcomes if o.status == "failed"]
    for outcome in failed:
        echo(f"pstoolkit: failed: {outcome.object} × {outcome.solver}: {outcome.error}", err=True)
    counts = status_counts(outcomes)
    if as_json:
        failures = [{"object": o.object, "solver": o.solver, "error": o.error} for o in failed]
        echo(json.dumps({"pairs": len(pairs), **counts, "out": str(out), "log": str(log), "failures": failures}, indent=2))
    else:
        echo(f"{len(pairs)} pairs: {counts['done']} done, {counts['skipped']} skipped, {counts['failed']} failed → {out} (log {log.name})")
    if failed:
        raise typer.Exit(1)
