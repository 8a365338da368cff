"""``pstoolkit integrate RESULT_DIR``: a surface from a result folder's normal map."""

from __future__ import annotations

from pathlib import Path

import typer

from pstoolkit.cli.app import QUIET_HELP, app, echo
from pstoolkit.plugin.manager import get_registries


@app.command("integrate")
def integrate_command(
    folder: Path = typer.Argument(..., help="A result folder (with result.json and normal.npy), as `pstoolkit run` writes it."),
    integrator: str = typer.Option("poisson", "--integrator", help="A registered integrator (see `pstoolkit plugins`)."),
    assignments: list[str] = typer.Option([], "--set", metavar="KEY=VALUE", help="An integrator option; repeat for more."),
    capture: Path | None = typer.Option(None, "--capture", help=(
        "The capture the result came from, for its ground-truth depth (the depth error) and camera; "
        "the path in result.json is not followed."
    )),
    as_json: bool = typer.Option(False, "--json", help="Print the new result.json."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help=QUIET_HELP),
) -> None:
    """Integrate the normal map of a result folder into a surface and add to the folder: depth.npy
    (float32 H×W, z towards the camera — frame pixels for an orthographic capture, NaN outside the
    mask), depth.png (16-bit, nearer is brighter, z = offset + (pixel − 1) / 65534 · scale, 0
    outside; offset and scale in result.json), mesh.ply (binary) and mesh.obj (a vertex per pixel,
    two triangles per 2×2 block, the albedo as vertex colours when the solver wrote one), and a
    surface entry in result.json (integrator, options, projection, seconds, files and, with
    --capture holding ground-truth depth, the RMSE after least-squares scale and offset alignment)."""
    # deferred: the integrators load scipy and the result writer OpenCV, which `pstoolkit --help` never needs
    from pstoolkit.io.textdata import summary_json
    from pstoolkit.surface.outputs import add_surface, folder_inputs, read_summary, surface_line

    entry = get_registries().integrators.get(integrator)
    options = entry.parse_options(assignments)
    summary = read_summary(folder)
    inputs = folder_inputs(folder, capture)
    summary = add_surface(folder, summary, inputs, entry, options)
    if as_json:
        echo(summary_json(summary))
        return
    echo(f"{folder}: {surface_line(summary['surface'])}")
