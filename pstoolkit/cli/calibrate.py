"""``pstoolkit calibrate affine TARGET.h5``: the event→frame affine from an LED-array target, stored in
captures; ``pstoolkit calibrate lights SOURCE -o DIR``: the light model from a chrome sphere, by a method
of the ``light calibrations`` registry, written as a light folder and stored in captures."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import typer

import psfmt
from pstoolkit.cli.app import QUIET_HELP, _Typer, app, echo
from pstoolkit.cli.help import PlainGroup
from pstoolkit.errors import UserError
from pstoolkit.plugin.manager import get_registries

if TYPE_CHECKING:
    from pstoolkit.hardware.calibrate import AffineFit


def _affine_text(affine: np.ndarray) -> str:
    return "[" + "; ".join(" ".join(f"{x:.5f}" for x in row) for row in affine) + "]"


calibrate_app = _Typer(
    name="calibrate",
    cls=PlainGroup,
    help="Calibrate a rig: the event→frame affine (affine) or the light model (lights).",
    no_args_is_help=True,
    rich_markup_mode=None,
)
app.add_typer(calibrate_app, name="calibrate")


@calibrate_app.command("affine")
def calibrate_affine_command(
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


def _choose_method(source: Path) -> str:
    """The first registered light calibration that takes ``source`` (built-ins: events before frames)."""
    registry = get_registries().light_calibrations
    for name in ("sphere-events", "sphere-frames", *registry.names()):
        if name in registry and registry.get(name).obj.accepts(source):
            return name
    raise UserError(f"{source}: no light calibration takes this source (give --method NAME)")


@calibrate_app.command("lights")
def calibrate_lights_command(
    source: Path = typer.Argument(..., help="The chrome sphere: a DiLiGenT-layout folder (one image per light) or a capture (frames or events)."),
    out: Path | None = typer.Option(None, "-o", "--out", help=(
        "Write the light folder here: light_directions.txt, light_intensities.txt, lights.json (the model, a --lights "
        "file for `convert raw/dat`) and calibration.json."
    )),
    method: str | None = typer.Option(None, "--method", help=(
        "A light calibration: sphere-frames, sphere-events or a plugin's (default: sphere-events for a capture with "
        "events, else sphere-frames); see `pstoolkit plugins`."
    )),
    sphere: str | None = typer.Option(None, "--sphere", help="The sphere's outline cx,cy,r in frame pixels (default: from the mask or silhouette)."),
    intrinsics: Path | None = typer.Option(None, "--intrinsics", help=(
        "K.txt, the 3×3 pinhole matrix of the frame camera (default: the capture's, else orthographic)."
    )),
    store: list[Path] = typer.Option([], "--store", help="Also set this capture's light model to the result; repeat for more."),
    assignments: list[str] = typer.Option([], "--set", metavar="KEY=VALUE", help="An option of the method (see `pstoolkit plugins`); repeat for more."),
    as_json: bool = typer.Option(False, "--json", help="Print the result as JSON: the model, the residual, the method's figures and what was written."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help=QUIET_HELP),
) -> None:
    """Measure the light model from a chrome sphere: each highlight located with sub-pixel precision and
    mirrored into a light direction (frames: one light per image, a sampled model; events: the highlight's
    track over the ring's turn fitted to the ring or near-ring model, with the fit's residual in degrees)."""
    from pstoolkit.hardware.lightcal import spec_json, store_lights, write_light_folder

    if not source.exists():
        raise UserError(f"{source}: does not exist")
    for path in store:
        if not path.is_file():
            raise UserError(f"--store {path}: does not exist")
    if out is not None:
        if out.exists() and not out.is_dir():
            raise UserError(f"-o {out}: exists and is not a folder")
        if out.resolve() == source.resolve() or source.resolve().is_relative_to(out.resolve()):
            raise UserError(f"-o {out}: would replace the source {source}")
    name = method or _choose_method(source)
    entry = get_registries().light_calibrations.get(name)
    pairs = list(assignments)
    for option, value in (("sphere", sphere), ("intrinsics", intrinsics)):
        if value is not None:
            if not any(o.name == option for o in entry.options):
                raise UserError(f"--{option}: light calibration {name!r} takes no {option}")
            pairs.append(f"{option}={value}")
    fit = entry.obj().calibrate(source, **entry.parse_options(pairs))
    report = {
        "method": name,
        "source": str(source),
        "lights": spec_json(fit.spec),
        "measured": len(fit.directions),
        "residual_deg": fit.residual_deg,
        **{k: v for k, v in fit.details.items() if k not in ("intensity",)},
    }
    if out is not None:
        write_light_folder(out, fit, report)
    for path in store:
        store_lights(path, fit)
    report["written"] = None if out is None else str(out)
    report["stored_in"] = [str(p) for p in store]
    if as_json:
        echo(json.dumps(report, indent=2, default=float))
        return
    if quiet:
        return
    residual = "" if fit.residual_deg is None else f", residual RMS {fit.residual_deg:.3f}°"
    scalars = ", ".join(f"{k} {v:g}" for k, v in fit.spec.params.items() if isinstance(v, (int, float)) and not isinstance(v, bool))
    line = f"{fit.spec.model} light model from {len(fit.directions)} highlight positions ({name}){residual}"
    if scalars:
        line += f": {scalars}"
    if out is not None:
        line += f"; wrote {out}"
    if store:
        line += "; stored in " + ", ".join(str(p) for p in store)
    echo(line)
