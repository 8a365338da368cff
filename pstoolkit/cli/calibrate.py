"""``pstoolkit calibrate TARGET.h5``: the event→frame affine from an LED-array target, stored in captures."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import typer

import psfmt
from pstoolkit.cli.app import QUIET_HELP, app, echo
from pstoolkit.errors import UserError

if TYPE_CHECKING:
    from pstoolkit.hardware.calibrate import AffineFit


def _affine_text(affine: np.ndarray) -> str:
    return "[" + "; ".join(" ".join(f"{x:.5f}" for x in row) for row in affine) + "]"


@app.command("calibrate")
def calibrate_command(
    target: Path = typer.Argument(..., help="A capture of the LED-array target: frames and events of the lit LEDs."),
    pairs: Path | None = typer.Option(None, "--pairs", help="Manual correspondences instead of detection: lines 'u_event v_event u_frame v_frame'."),
    frame: int | None = typer.Option(None, "--frame", help="Detect the LEDs in this frame (default: the mean of all frames)."),
    level: float = typer.Option(0.5, "--level", help="Blob threshold as a fraction from background to the brightest pixel."),
    tolerance_px: float | None = typer.Option(None, "--tolerance-px", help="Match radius in frame pixels (default: a quarter of the LED spacing)."),
    max_error_px: float = typer.Option(1.0, "--max-error-px", help="Refuse to store an affine whose RMS reprojection error exceeds this (frame pixels)."),
    apply_to: list[Path] = typer.Option([], "--apply-to", help="Also store the affine in this capture; repeat for more."),
    store: bool = typer.Option(True, "--store/--no-store", help="Store the affine in TARGET (and --apply-to captures) or only print it."),
    as_json: bool = typer.Option(False, "--json", help=(
        "Print the result as JSON: the affine, the reprojection errors, what it was fitted from and where it was stored."
    )),
    quiet: bool = typer.Option(False, "--quiet", "-q", help=QUIET_HELP),
) -> None:
    """Estimate the 2×3 event→frame affine from LED blobs seen by both cameras (robust matching,
    least squares), report the reprojection error, and store it in the capture(s) atomically."""
    # deferred: blob detection loads scipy, which `pstoolkit --help` never needs
    from pstoolkit.hardware.calibrate import calibrate_target, fit_affine, read_pairs, store_affine

    for path in [target, *apply_to]:
        if not path.exists():
            raise UserError(f"{path}: does not exist")
    if not 0 < level < 1:
        raise UserError(f"--level {level:g} must be between 0 and 1")
    fit: AffineFit
    if pairs is not None:
        fit = fit_affine(*read_pairs(pairs))
        source = f"{fit.pairs} manual pairs"
    else:
        with psfmt.read(target) as capture:
            fit = calibrate_target(capture, frame=frame, level=level, tolerance_px=tolerance_px)
        source = f"{fit.pairs} LED pairs ({fit.frame_blobs} frame blobs, {fit.event_blobs} event blobs)"
    if fit.rms_px > max_error_px:
        raise UserError(
            f"{target}: reprojection error RMS {fit.rms_px:.3f} px exceeds --max-error-px {max_error_px:g} "
            "(adjust the cameras and record again, or give --pairs); nothing stored"
        )
    line = f"event→frame affine from {source}: reprojection error RMS {fit.rms_px:.3f} px, max {fit.max_px:.3f} px; {_affine_text(fit.affine)}"
    stored_in = [target, *apply_to] if store else []
    for path in stored_in:
        store_affine(path, fit.affine)
    if as_json:
        echo(json.dumps({
            "affine": np.asarray(fit.affine, dtype=float).tolist(),
            "rms_px": float(fit.rms_px),
            "max_px": float(fit.max_px),
            "pairs": fit.pairs,
            "from": "pairs file" if pairs is not None else "LED detection",
            "frame_blobs": None if pairs is not None else fit.frame_blobs,
            "event_blobs": None if pairs is not None else fit.event_blobs,
            "stored_in": [str(p) for p in stored_in],
        }, indent=2))
        return
    if stored_in:
        line += "; stored in " + ", ".join(str(p) for p in stored_in)
    echo(line)
