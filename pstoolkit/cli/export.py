"""``pstoolkit export CAPTURE --events evt3|evt2|dat|dsec -o FILE``: a capture's events as an event file;
``pstoolkit export CAPTURE --frames diligent -o DIR``: a classic capture as a DiLiGenT object folder.

The events stream from the capture in blocks and the frames are written one at a time, so a capture
of any size exports in bounded memory.
"""

from __future__ import annotations

import json
from pathlib import Path

import typer

import psfmt
from psfmt.atomic import check_target
from pstoolkit.cli.app import app, echo, progress_bar
from pstoolkit.errors import UserError

EVENT_FORMATS = ("evt3", "evt2", "dat", "dsec")
FRAME_FORMATS = ("diligent",)


@app.command()
def export(
    capture_file: Path = typer.Argument(..., metavar="CAPTURE", help="A hybrid-capture HDF5 file."),
    events: str | None = typer.Option(None, "--events", help="Write the events: evt3 or evt2 (Prophesee RAW), dat (Metavision DAT) or dsec (HDF5) file OUT."),
    frames: str | None = typer.Option(None, "--frames", help=(
        "Write the frames of a classic capture (instantaneous lights): diligent, a DiLiGenT object folder OUT (16-bit "
        "PNGs, filenames.txt, light_directions.txt, light_intensities.txt, mask.png, Normal_gt.mat with ground truth)."
    )),
    out: Path = typer.Option(..., "-o", "--out", help="File (--events) or folder (--frames) to write."),
    compression: str = typer.Option("gzip", "--compression", help="dsec only: gzip, zstd (needs hdf5plugin) or none."),
    force: bool = typer.Option(False, "--force", help="--frames: replace a non-empty OUT folder (as a unit, once the new one is complete)."),
    as_json: bool = typer.Option(False, "--json", help="Print what was written as JSON and no progress."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar and no summary line."),
) -> None:
    """Write a capture's events as a Prophesee RAW file (EVT 3.0 or EVT 2.0), a Metavision DAT file or a
    DSEC-style HDF5 file (--events), or a classic capture's frames as a DiLiGenT object folder (--frames diligent) that
    `pstoolkit convert diligent` reads back. Give exactly one of --events and --frames."""
    if (events is None) == (frames is None):
        raise UserError("give exactly one of --events FORMAT and --frames FORMAT")
    if frames is not None:
        if compression != "gzip":
            raise UserError("--compression is for --events dsec only")
        _export_frames(capture_file, frames, out, force, quiet, as_json)
    else:
        assert events is not None
        _export_events(capture_file, events, out, compression, quiet, as_json)


def _export_frames(capture_file: Path, fmt: str, out: Path, force: bool, quiet: bool, as_json: bool) -> None:
    from pstoolkit.io.diligent_export import export_diligent

    if fmt not in FRAME_FORMATS:
        raise UserError(f"--frames {fmt!r} is not one of {', '.join(FRAME_FORMATS)}")
    written = export_diligent(capture_file, out, force=force, progress=progress_bar(f"export {capture_file.name}", quiet or as_json))
    if as_json:
        echo(json.dumps({
            "folder": str(written.folder),
            "format": fmt,
            "images": written.images,
            "width": written.width,
            "height": written.height,
            "mask_source": written.mask_source,
            "normal_gt": bool(written.normal),
        }, indent=2))
    elif not quiet:
        extra = ", Normal_gt.mat" if written.normal else ""
        echo(
            f"wrote {written.folder}: {written.images} images at {written.width}×{written.height}, "
            f"mask from the {written.mask_source}{extra}"
        )


def _export_events(capture_file: Path, fmt: str, out: Path, compression: str, quiet: bool, as_json: bool) -> None:
    # the codecs load here, so that other commands start without numba's import
    from psfmt.eventfiles.dat import write_dat
    from psfmt.eventfiles.dsec import write_dsec
    from psfmt.eventfiles.evt2 import write_raw as write_evt2
    from psfmt.eventfiles.evt3 import write_raw as write_evt3

    if fmt not in EVENT_FORMATS:
        raise UserError(f"--events {fmt!r} is not one of {', '.join(EVENT_FORMATS)}")
    if not out.parent.is_dir():
        raise UserError(f"{out}: folder {out.parent} does not exist")
    check_target(out, [capture_file])
    with psfmt.read(capture_file) as capture:
        stream = capture.events
        if stream is None:
            raise UserError(f"{capture_file}: holds no events to export")
        try:
            if fmt == "evt3":
                write_evt3(out, stream.chunks(), stream.width, stream.height)
            elif fmt == "evt2":
                write_evt2(out, stream.chunks(), stream.width, stream.height)
            elif fmt == "dat":
                write_dat(out, stream.chunks(), stream.width, stream.height)
            else:
                write_dsec(out, stream.chunks(), len(stream), stream.width, stream.height, compression=compression)
        except psfmt.FormatError:
            raise
        except ValueError as exc:  # the encoders' word on events they cannot hold
            raise UserError(f"{capture_file}: cannot export as {fmt}: {exc}") from None
    if as_json:
        echo(json.dumps({"file": str(out), "format": fmt, "events": len(stream), "bytes": out.stat().st_size}, indent=2))
    elif not quiet:
        echo(f"wrote {out} ({len(stream):,} events, {out.stat().st_size:,} bytes)")
