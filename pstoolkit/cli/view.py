"""``pstoolkit view RESULT_DIR|CAPTURE.h5``: a local relighting viewer in the browser."""

from __future__ import annotations

import errno
import webbrowser
from pathlib import Path

import typer

from pstoolkit.cli.app import app, echo
from pstoolkit.errors import UserError


@app.command()
def view(
    path: Path = typer.Argument(..., help="A result folder written by `pstoolkit run`, or a capture file (.h5)."),
    port: int = typer.Option(8765, "--port", help="TCP port to serve on (0: any free port)."),
    host: str = typer.Option("127.0.0.1", "--host", help="Address to bind; one that is not loopback needs --allow-remote."),
    allow_remote: bool = typer.Option(False, "--allow-remote", help="Allow a --host other than loopback: anyone who reaches it can read the result."),
    no_browser: bool = typer.Option(False, "--no-browser", help="Only print the address; do not open a browser."),
    capture: Path | None = typer.Option(
        None, "--capture", help="With a result folder: its capture, to scrub the frames and events (the path in result.json is not followed)."
    ),
    result: str | None = typer.Option(
        None, "--result", help="With a capture: the stored result to show (default: the first one stored, else the ground truth)."
    ),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No notes on stderr (the address is still printed)."),
) -> None:
    """Serve a page on this machine that shows a result's maps side by side (normal, albedo, F0,
    roughness, error and depth, whichever exist); relights the surface with the toolkit's BRDF
    (GGX with F0 and roughness maps, else Lambertian) under a light you drag on a disc; scrubs the
    capture's frames and events over time beside the result rendered under the capture's light at
    that time (when the capture is known); and turns the depth map, if there is one, as a point
    cloud you drag. It binds 127.0.0.1 unless --host says otherwise (an address that is not
    loopback needs --allow-remote), serves no file from outside the result folder, and stops at
    Ctrl-C."""
    from pstoolkit.view.server import ViewServer, check_bind
    from pstoolkit.view.source import load_capture_maps, load_result_folder
    from pstoolkit.view.timeline import Timeline

    check_bind(host, allow_remote)  # first: no reading of files for a server that may not start
    if not 0 <= port <= 65535:
        raise UserError(f"--port {port}: expected 0 to 65535")
    timeline = None
    if path.is_dir():
        if result is not None:
            raise UserError("--result picks a result stored in a capture; a result folder holds one")
        data = load_result_folder(path, capture)
        if data.capture is not None:
            timeline = Timeline(data.capture, (data.height, data.width))
    elif path.is_file():
        if capture is not None:
            raise UserError("--capture goes with a result folder; PATH is a capture already")
        timeline = Timeline(path)
        try:
            data = load_capture_maps(timeline.capture, path, result)
        except BaseException:
            timeline.close()
            raise
    else:
        raise UserError(f"{path}: no such file or folder")
    try:
        server = ViewServer(data, timeline, host=host, port=port, allow_remote=allow_remote)
    except OSError as exc:
        if timeline is not None:
            timeline.close()
        if exc.errno == errno.EADDRINUSE:
            raise UserError(f"port {port} on {host} is in use: pick another with --port (0: any free port)") from None
        raise UserError(f"cannot serve on {host}:{port}: {exc.strerror or exc}") from None
    for note in [] if quiet else data.notes:
        echo(f"note: {note}", err=True)
    echo(f"serving {data.label} at {server.url} (Ctrl-C to stop)")
    if not no_browser:
        webbrowser.open(server.url)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        if not quiet:
            echo("stopped", err=True)  # Ctrl-C is how a server is meant to stop: not an error
    finally:
        server.server_close()
        if timeline is not None:
            timeline.close()
