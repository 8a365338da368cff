"""``pstoolkit export CAPTURE --events evt3|evt2|dsec -o FILE``: a capture's events as an event file.

The events stream from the capture in blocks, so a capture of any size exports in bounded memory.
"""

from __future__ import annotations

from pathlib import Path

import typer

import psfmt
from pstoolkit.cli.app import app
from pstoolkit.errors import UserError

EVENT_FORMATS = ("evt3", "evt2", "dsec")


@app.command()
def export(
    capture_file: Path = typer.Argument(..., metavar="CAPTURE", help="A hybrid-capture HDF5 file with events."),
    events: str = typer.Option(..., "--events", help="Event file format: evt3 or evt2 (Prophesee RAW) or dsec (HDF5)."),
    out: Path = typer.Option(..., "-o", "--out", help="File to write."),
    compression: str = typer.Option("gzip", "--compression", help="dsec only: gzip, zstd (needs hdf5plugin) or none."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No summary line."),
) -> None:
    """Write a capture's events as a Prophesee RAW file (EVT 3.0 or EVT 2.0) or a DSEC-style HDF5 file."""
    # the codecs load here, so that other commands start without numba's import
    from psfmt.dsec import write_dsec
    from psfmt.evt2 import write_raw as write_evt2
    from psfmt.evt3 import write_raw as write_evt3

    if events not in EVENT_FORMATS:
        raise UserError(f"--events {events!r} is not one of {', '.join(EVENT_FORMATS)}")
    if not out.parent.is_dir():
        raise UserError(f"{out}: folder {out.parent} does not exist")
    with psfmt.read(capture_file) as capture:
        stream = capture.events
        if stream is None:
            raise UserError(f"{capture_file}: holds no events to export")
        try:
            if events == "evt3":
                write_evt3(out, stream.chunks(), stream.width, stream.height)
            elif events == "evt2":
                write_evt2(out, stream.chunks(), stream.width, stream.height)
            else:
                write_dsec(out, stream.chunks(), len(stream), stream.width, stream.height, compression=compression)
        except psfmt.FormatError:
            raise
        except ValueError as exc:  # the encoders' word on events they cannot hold
            raise UserError(f"{capture_file}: cannot export as {events}: {exc}") from None
    if not quiet:
        typer.echo(f"wrote {out} ({len(stream):,} events, {out.stat().st_size:,} bytes)")
