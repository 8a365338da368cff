"""``pstoolkit run [CAPTURE] --solver NAME``: run a registered solver and write its outputs."""

from __future__ import annotations

import re
from pathlib import Path

import typer

import psfmt
from pstoolkit._shared.progress import Progress
from pstoolkit.cli.app import app, echo, progress_bar
from pstoolkit.cli.config import check_capture, config_option, integrator_assignments_of, solver_assignments
from pstoolkit.errors import UserError
from pstoolkit.plugin.manager import get_registries
from pstoolkit.solve.base import check_tiling, resolve_device, resolve_options
from pstoolkit.version import __version__

_RESULT_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]*")


def _demo_capture(progress: Progress, note: bool) -> Path:
    # Deferred: the demo module loads the simulator (and torch), which a run on a given file never needs.
    from pstoolkit.sim import demo

    if note:
        echo("no CAPTURE given: running on the built-in demo capture (simulated on first use, then cached)", err=True)
    return demo.demo_capture_path(demo.DEMO_CONFIG, progress)


@app.command()
def run(
    ctx: typer.Context,
    capture: Path | None = typer.Argument(None, help="A hybrid-capture HDF5 file (default: the built-in demo capture)."),
    solver: str = typer.Option(..., "--solver", help="A registered solver (see `pstoolkit plugins`)."),
    out: Path | None = typer.Option(None, "-o", "--out", help="Output folder (default: out/<capture stem>-<name>)."),
    assignments: list[str] = typer.Option([], "--set", metavar="KEY=VALUE", help="A solver option; repeat for more."),
    device: str = typer.Option("auto", "--device", help="auto (CUDA when available), cpu or cuda."),
    scheduler: str | None = typer.Option(None, "--scheduler", help=(
        "A tiled solver (dualres): send its tiles to the Dask scheduler at this address (tcp://host:8786); "
        "default: a local cluster when the capture is cut into tiles."
    )),
    workers: int | None = typer.Option(None, "--workers", help=(
        "A tiled solver: worker processes of the local cluster (default: one per CPU core; at most four per core)."
    )),
    as_json: bool = typer.Option(False, "--json", help="Print result.json and no progress."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar and no notes on stderr (the summary line is still printed)."),
    store: bool = typer.Option(False, "--store/--no-store", help="Also store the maps in the capture under /results/<name>."),
    name: str | None = typer.Option(None, "--name", help=(
        "Name of the result: its column in `pstoolkit eval` and /results/<name> with --store (default: the solver)."
    )),
    error_max: float = typer.Option(30.0, "--error-max", help="Angular error (degrees, above 0 and at most 180) at the top of error.png's colour scale."),
    integrate: str | None = typer.Option(None, "--integrate", help=(
        "Also integrate the normals into a surface with this registered integrator (see `pstoolkit plugins`): "
        "depth.npy, depth.png, mesh.ply, mesh.obj and a surface entry in result.json."
    )),
    integrator_assignments: list[str] = typer.Option([], "--integrator-set", metavar="KEY=VALUE", help="An integrator option; repeat for more."),
    config: Path | None = config_option("run"),
) -> None:
    """Estimate normals of CAPTURE with a solver. Writes to the output folder: normal.npy (float32
    H×W×3), normal.png (16-bit, RGB = (n+1)/2, x right, y up, z to the camera, background 0), each
    further map of the solver as <map>.png (16-bit, scale in result.json) and <map>.npy, error.png
    (Turbo colormap, 0 to --error-max degrees, black outside the mask, grey where the solver left a
    pixel unsolved) and error.npy (float32 degrees, NaN outside the mask, 90 where unsolved) when the
    capture has ground truth, and result.json (solver, capture, seconds, mean and median error in
    degrees with unsolved pixels counted as 90°, coverage and the mean error of the solved pixels,
    shares below 11.25/22.5/30°, data rate, options). With --integrate, also the surface (see
    `pstoolkit integrate --help`), with its depth error when the capture has ground-truth depth.
    The output folder is replaced as a unit: no file of an earlier result stays. With --config FILE,
    the settings come from a TOML file or an earlier run's result.json (docs/config.md)."""
    # deferred: writing maps loads OpenCV and integrating loads scipy, which `pstoolkit --help` never needs
    from pstoolkit.io.textdata import summary_json
    from pstoolkit.solve.results import check_error_max, check_result_folder, result_folder, result_summary, solve_capture, write_result_folder
    from pstoolkit.surface.outputs import SurfaceInputs, add_surface, capture_truth, surface_line

    entry = get_registries().solvers.get(solver)
    # resolved (presets expanded) before the run: result.json records the values the run used
    options = resolve_options(entry, entry.parse_options(solver_assignments(ctx, entry, assignments)))
    integrator = None if integrate is None else get_registries().integrators.get(integrate)
    integrator_assignments = integrator_assignments_of(ctx, integrator, integrator_assignments)
    integrator_options = {} if integrator is None else integrator.parse_options(integrator_assignments)
    if integrator is None and integrator_assignments:
        raise UserError("--integrator-set needs --integrate NAME")
    check_tiling(entry, scheduler, workers)
    device = resolve_device(device)
    check_error_max(error_max, "--error-max")
    result_name = entry.name if name is None else name
    if not _RESULT_NAME.fullmatch(result_name):
        raise UserError(f"--name {result_name!r}: use letters, digits, '.', '_' and '-', starting with a letter or digit")
    notes = not quiet  # the lines on stderr besides the result: the demo capture, the stored result
    quiet = quiet or as_json  # and no progress bar with --json either
    demo = capture is None
    check_capture(ctx, capture)
    obj = "demo" if demo else capture.stem
    outdir = out if out is not None else Path("out") / f"{obj}-{result_name}"
    check_result_folder(outdir, [] if capture is None else [capture])  # before solving, so that a long run does not end in this error
    if capture is None:
        capture = _demo_capture(progress_bar("simulate demo", quiet), notes)
    solved = solve_capture(entry, capture, options, device=device, scheduler=scheduler, workers=workers,
                           progress=progress_bar(entry.name, quiet))
    if store:
        stored = psfmt.Result(
            name=result_name,
            maps={"normal": solved.normal, "mask": solved.mask, **{m.name: m.array for m in solved.maps}},
            solver=entry.name,
            options=options,
            seconds=solved.seconds,
            version=__version__,
            data_rate=solved.data_rate,
        )
        psfmt.write_result(capture, stored)
        where = f"the demo capture {capture} (a cached file, regenerated without it if the cache is cleared)" if demo else str(capture)
        if notes:
            echo(f"stored result {result_name!r} in {where}", err=True)
    # after storing: result.json records the capture's checksum as the file is now
    summary = result_summary(
        solved, entry=entry, name=result_name, obj=obj, capture=capture, device=device, options=options, error_max_deg=error_max, stored=store
    )
    with result_folder(outdir) as partial:
        text = write_result_folder(partial, solved, summary)
        if integrator is not None:
            albedo = next((m.array for m in solved.maps if m.name == "albedo" and m.array.shape == (*solved.mask.shape, 3)), None)
            truth, camera = capture_truth(capture, solved.mask.shape)
            inputs = SurfaceInputs(solved.normal, solved.mask, albedo, truth, camera)
            summary = add_surface(partial, summary, inputs, integrator, integrator_options)
            text = summary_json(summary)
    if as_json:
        echo(text)
        return
    score_text = (
        f"MAE {summary['mae_deg']:.2f}°, median {summary['median_deg']:.2f}°, coverage {100 * summary['coverage']:.1f} %"
        if solved.scored is not None
        else "no ground truth"
    )
    echo(f"{entry.name} on {capture}: {score_text}, {solved.seconds:.2f} s, data rate {100 * solved.data_rate:.1f} % → {outdir}")
    if integrator is not None:
        echo(surface_line(summary["surface"]))
