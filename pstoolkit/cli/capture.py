"""``pstoolkit capture --light ringlight --port PORT|sim --source replay:FILE -o OUT.h5``: record a capture.

Configures the light, starts the camera sources, streams them into ``psfmt.CaptureWriter`` for
``--periods`` turns from the light's first period trigger, and stores the light model and the
calibration. Ctrl-C, a device fault or a source that ends early leave the lights off and no file at
OUT (an earlier file there stays as it was).
"""

from __future__ import annotations

import dataclasses
import json
from contextlib import ExitStack
from pathlib import Path

import numpy as np
import typer

import psfmt
from pstoolkit.cli.app import app, echo, progress_bar
from pstoolkit.errors import Interrupted, UserError
from pstoolkit.hardware.backend import (
    TRIGGER_MODES,
    CameraSource,
    LightBackend,
    Sweep,
    backend_class,
    record,
)
from pstoolkit.plugin.manager import get_registries
from pstoolkit.plugin.options import parse_assignments
from pstoolkit.version import __version__

DEFAULT_PERIOD_MS = 1000.0 / 30.0
DIRECTIONS = {"ccw": 1, "cw": -1}


def _sources(specs: list[str], pairs: list[str]) -> list[CameraSource]:
    """``NAME:LOCATION`` specs → source objects; each takes the ``--source-set`` keys it declares."""
    backends = get_registries().backends
    made: list[CameraSource] = []
    used: set[str] = set()
    for spec in specs:
        name, sep, location = spec.partition(":")
        if not sep or not name or not location:
            raise UserError(f"--source {spec!r}: expected NAME:LOCATION (e.g. replay:recording.h5)")
        entry = backends.get(name)
        cls = backend_class(entry, "source")
        known = {o.name for o in entry.options}
        mine = [p for p in pairs if p.partition("=")[0].strip() in known]
        used.update(mine)
        made.append(cls(location, parse_assignments(mine, entry.options, owner=f"source {name!r}")))
    unused = [p for p in pairs if p not in used]
    if unused:
        raise UserError(f"--source-set {unused[0]!r}: no source given has option {unused[0].partition('=')[0].strip()!r}")
    return made


def _period_us(period_ms: float | None, sources: list[CameraSource]) -> int:
    """The light period: --period-ms, else the one a source dictates (a replay), else 30 turns/s."""
    dictated = {s.period_us for s in sources if s.period_us is not None}
    if len(dictated) > 1:
        raise UserError(f"the sources were recorded with different light periods ({', '.join(map(str, sorted(dictated)))} µs)")
    if period_ms is not None:
        if period_ms <= 0:
            raise UserError(f"--period-ms {period_ms:g} must be positive")
        return round(period_ms * 1000.0)
    return dictated.pop() if dictated else round(DEFAULT_PERIOD_MS * 1000.0)


def _stored_affine(path: Path) -> psfmt.Calibration:
    if not path.exists():
        raise UserError(f"--calibration {path}: does not exist")
    with psfmt.read(path) as capture:
        if capture.calibration.event_to_frame is None:
            raise UserError(f"--calibration {path}: holds no event_to_frame affine (run `pstoolkit calibrate affine {path}` first)")
        return capture.calibration


def _begin(writer: psfmt.CaptureWriter, sources: list[CameraSource]) -> None:
    frame_sources = [s for s in sources if s.frame_sensor is not None]
    event_sources = [s for s in sources if s.event_sensor is not None]
    if len(frame_sources) > 1 or len(event_sources) > 1:
        raise UserError("more than one source delivers frames (or events); a capture holds one frame and one event camera")
    if frame_sources:
        f = frame_sources[0].frame_sensor
        assert f is not None
        writer.begin_frames(
            f.height, f.width, f.channels, f.dtype,
            color_order=f.color_order, bit_depth=f.bit_depth, saturation=f.saturation, black_level=f.black_level,
        )
    if event_sources:
        e = event_sources[0].event_sensor
        assert e is not None
        writer.begin_events(e.width, e.height)


def _calibration(sources: list[CameraSource], given: psfmt.Calibration | None) -> psfmt.Calibration:
    found = next((s.calibration for s in sources if s.calibration is not None), None)
    cal = dataclasses.replace(found) if found is not None else psfmt.Calibration()
    sensor = next((s.event_sensor for s in sources if s.event_sensor is not None), None)
    if sensor is not None:
        cal.contrast_pos = sensor.contrast_pos if sensor.contrast_pos is not None else cal.contrast_pos
        cal.contrast_neg = sensor.contrast_neg if sensor.contrast_neg is not None else cal.contrast_neg
        cal.refractory_us = sensor.refractory_us if sensor.refractory_us is not None else cal.refractory_us
    if given is not None:
        cal.event_to_frame = given.event_to_frame
    return cal


@app.command("capture")
def capture_command(
    light: str = typer.Option(..., "--light", help="A registered light backend: ringlight or a plugin's."),
    port: str = typer.Option(..., "--port", help="The light's serial port or pyserial URL (/dev/ttyACM0, COM3, rfc2217://host:port), or sim."),
    source: list[str] = typer.Option(..., "--source", help="A camera source as NAME:LOCATION (replay:recording.h5); repeat for more cameras."),
    out: Path = typer.Option(..., "-o", "--out", help="The capture file to write (HDF5)."),
    periods: int = typer.Option(1, "--periods", help="Light turns to record, from the first period trigger."),
    period_ms: float | None = typer.Option(None, "--period-ms", help="One turn of the light, ms (default: the replayed recording's, else 33.333)."),
    direction: str = typer.Option("ccw", "--direction", help="Sweep direction seen from the camera: ccw or cw."),
    smooth: bool = typer.Option(True, "--smooth/--steps", help="Blend neighbouring LEDs (continuous light) or light one LED at a time."),
    trigger: str = typer.Option("period", "--trigger", help="Camera trigger output: period (one pulse per turn), exposure (one per exposure window) or off."),
    exposures: int = typer.Option(3, "--exposures", help="Exposure windows per turn, for --trigger exposure."),
    calibration: Path | None = typer.Option(None, "--calibration", help="A capture whose event→frame affine (from `pstoolkit calibrate`) to store."),
    assignments: list[str] = typer.Option([], "--set", metavar="KEY=VALUE", help="A light option (see `pstoolkit plugins`); repeat for more."),
    source_assignments: list[str] = typer.Option([], "--source-set", metavar="KEY=VALUE", help=(
        "A source option (replay: speed=0, slice_us=500); repeat for more."
    )),
    description: str = typer.Option("", "--description", help="Free text stored in the file."),
    as_json: bool = typer.Option(False, "--json", help="Print what was recorded as JSON (file, frames, events, periods) and no progress."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar and no summary line."),
) -> None:
    """Record a capture from a light rig and camera sources (or a replayed recording) into OUT.h5."""
    if periods < 1:
        raise UserError(f"--periods {periods} must be at least 1")
    if direction not in DIRECTIONS:
        raise UserError(f"--direction {direction!r}: expected ccw or cw")
    if trigger not in TRIGGER_MODES:
        raise UserError(f"--trigger {trigger!r}: expected one of {', '.join(TRIGGER_MODES)}")
    if not 1 <= exposures <= 100:
        raise UserError(f"--exposures {exposures} must be between 1 and 100")
    entry = get_registries().backends.get(light)
    light_cls = backend_class(entry, "light")
    light_options = entry.parse_options(assignments)
    sources = _sources(source, source_assignments)
    given = _stored_affine(calibration) if calibration is not None else None
    progress = progress_bar("capture", quiet or as_json)
    try:
        with ExitStack() as stack:
            for s in sources:
                stack.enter_context(s)
            sweep = Sweep(_period_us(period_ms, sources), DIRECTIONS[direction], smooth, trigger, exposures)
            writer = stack.enter_context(
                psfmt.CaptureWriter(out, description=description, creator="pstoolkit capture", creator_version=__version__)
            )
            _begin(writer, sources)
            rig: LightBackend = stack.enter_context(light_cls(port, light_options))
            rig.configure(sweep)
            rig.start()
            done = record(sources, writer, sweep, periods, rig.keepalive, rig.keepalive_s, progress=progress)
            rig.stop()
            writer.set_lights(rig.light_spec(sweep, done.t0_us))
            writer.set_calibration(_calibration(sources, given))
            if done.triggers:
                writer.set_triggers(*(np.concatenate([getattr(b, c) for b in done.triggers]) for c in ("t", "channel", "value")))
    except KeyboardInterrupt:
        # leaving the block sent the light OFF (on a dead link its watchdog turns them off) and removed
        # the writer's temporary file
        raise Interrupted(f"the lights are off and {out} was not written") from None
    if as_json:
        echo(json.dumps({"file": str(out), "frames": done.frames, "events": done.events, "periods": periods, "period_us": sweep.period_us}, indent=2))
    elif not quiet:
        echo(f"wrote {out}: {done.frames} frames, {done.events:,} events, {periods} period(s) of {sweep.period_us} µs")
