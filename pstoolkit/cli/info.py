"""``pstoolkit info FILE``: what a capture holds, in a few lines (or JSON)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import typer

import psfmt
from psfmt.text import printable
from pstoolkit.cli.app import QUIET_HELP, app, echo


def describe(capture: psfmt.Capture) -> dict[str, Any]:
    """A JSON-able summary: geometry, frames, events, lights, ground truth, results and data rate."""
    out: dict[str, Any] = {
        "file": str(capture.path) if capture.path else None,
        "kind": capture.kind,
        "format_version": capture.format_version,
        "creator": f"{capture.creator} {capture.creator_version}".strip(),
        "created": capture.created,
        "description": capture.description,
    }
    frames = capture.frames
    if frames is not None:
        f: dict[str, Any] = {
            "count": frames.count,
            "width": frames.width,
            "height": frames.height,
            "channels": frames.channels,
            "dtype": str(frames.data.dtype),
            "bit_depth": frames.bit_depth,
            "saturation": frames.saturation,
            "black_level": frames.black_level,
        }
        if frames.has_windows:
            exposure = (frames.t_end_us - frames.t_start_us) / 1000.0
            f["exposure_ms"] = [round(float(v), 3) for v in exposure]
        else:
            f["instantaneous_lights"] = True
        out["frames"] = f
    out["camera"] = camera(capture.calibration)
    events = capture.events
    if events is not None:
        n = len(events)
        duration_s = (events.t_last_us - events.t_first_us + 1) / 1e6 if n else 0.0
        out["events"] = {
            "count": n,
            "width": events.width,
            "height": events.height,
            "t_first_us": events.t_first_us,
            "t_last_us": events.t_last_us,
            "duration_s": duration_s,
            "rate_ev_per_s": n / duration_s if duration_s > 0 else 0.0,
        }
        calibration = capture.calibration
        out["event_sensor"] = {
            "contrast_pos": calibration.contrast_pos,
            "contrast_neg": calibration.contrast_neg,
            "refractory_us": calibration.refractory_us,
            # a capture that records no rule has the format's default (spec §9)
            "refractory_rule": calibration.refractory_rule or psfmt.REFRACTORY_RULES[0],
            "refractory_rule_recorded": calibration.refractory_rule is not None,
            **event_to_frame(capture),
        }
    if capture.calibration.sensor_model is not None:
        out["sensor_model"] = dict(capture.calibration.sensor_model)
    if capture.lights is not None:
        out["lights"] = {
            "model": capture.lights.model,
            "params": {k: v for k, v in capture.lights.params.items() if isinstance(v, (int, float, str, bool))},
        }
    gt = capture.ground_truth
    if gt is not None:
        out["ground_truth"] = [k for k in ("normal", "mask", "albedo", "depth") if getattr(gt, k) is not None] + sorted(gt.materials)
    out["results"] = {name: {"solver": r.solver, "seconds": r.seconds} for name, r in capture.results.items()}
    rate = psfmt.data_rate(capture)
    out["data_rate"] = {
        "total": rate.rate,
        "frames": rate.frame_rate,
        "events": rate.event_rate,
        "periods": rate.periods,
        "accounting": "per light period; frames as 24-bit RGB, events as 16-bit EVT 3.0 words; 1.0 = 24 RGB frames",
    }
    if events is not None:
        out["event_encoding"] = event_encoding(capture)
    return out


def event_to_frame(capture: psfmt.Capture) -> dict[str, Any]:
    """The 2×3 affine from event pixel centres (u_e, v_e, 1) to target (frame) pixel coordinates as
    rows of numbers (``event_to_frame``), and whether the calibration records it
    (``event_to_frame_recorded``); when it does not, the one the solvers assume: an event sensor that
    sees the target's field of view (``pstoolkit.grid.default_affine``)."""
    from pstoolkit.grid import default_affine  # here: info otherwise needs nothing of pstoolkit's maths

    recorded = capture.calibration.event_to_frame
    assert capture.events is not None
    affine = recorded if recorded is not None else default_affine(capture.events.width, psfmt.target_size(capture)[1])
    return {"event_to_frame": [[float(v) for v in row] for row in affine], "event_to_frame_recorded": recorded is not None}


def camera(calibration: psfmt.Calibration) -> dict[str, Any]:
    """The camera model and, for a perspective camera, fx, fy, cx, cy (and the skew s) of its
    intrinsics K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]] in frame pixels (spec §9.1)."""
    out: dict[str, Any] = {"model": calibration.camera_model}
    if calibration.intrinsics is not None:
        k = calibration.intrinsics
        out.update(fx=float(k[0, 0]), fy=float(k[1, 1]), cx=float(k[0, 2]), cy=float(k[1, 2]), skew=float(k[0, 1]))
    return out


NUMPY_SIZING_EVENTS = 2_000_000
"""Up to this many events ``info`` sizes the EVT 3.0 encoding with numpy (measured on 2 cores: about
0.2 s per million events) rather than numba (about 0.5 s to import and load, then 0.01 s per million)."""


def event_encoding(capture: psfmt.Capture) -> dict[str, Any]:
    """The real EVT 3.0 size of the capture's events (words only, no header) beside the 16-bit
    estimate, and the data rate with the real size."""
    from psfmt.eventfiles.evt3 import encoded_size  # here, so that other commands start without the codec

    assert capture.events is not None
    # the numpy encoder up to a few million events: the compiled one would first spend half a second
    # importing numba and loading its kernel, more than numpy takes for the whole stream
    engine = "numpy" if len(capture.events) <= NUMPY_SIZING_EVENTS else "auto"
    evt3 = encoded_size(capture.events.chunks(), engine=engine)
    rate = psfmt.data_rate(capture, event_bytes=evt3)
    return {
        "evt3_bytes": evt3,
        "estimate_bytes": 2 * len(capture.events),
        "bytes_per_event": evt3 / len(capture.events) if len(capture.events) else 0.0,
        "data_rate_total": rate.rate,
        "data_rate_events": rate.event_rate,
    }


def _text(d: dict[str, Any]) -> str:
    """The summary as lines; every string from the file is made one printable line (``printable``)."""
    s = printable
    lines = [f"{s(d['file'])}: {d['kind']} capture, format {s(d['format_version'])}, by {s(d['creator'])} at {s(d['created'])}"]
    if d["description"]:
        lines.append(f"  description: {s(d['description'])}")
    if "frames" in d:
        f = d["frames"]
        black = f", black level {f['black_level']:g}" if f["black_level"] else ""
        timing = (
            "exposure " + ", ".join(f"{e:g}" for e in f["exposure_ms"]) + " ms"
            if "exposure_ms" in f
            else "instantaneous lights"
        )
        lines.append(
            f"  frames: {f['count']} × {f['width']}×{f['height']}×{f['channels']} {f['dtype']} "
            f"({f['bit_depth']}-bit, saturation {f['saturation']:g}{black}), {timing}"
        )
    cam = d["camera"]
    if "fx" in cam:
        skew = f", skew {cam['skew']:g}" if cam["skew"] else ""
        lines.append(f"  camera: {s(cam['model'])}, fx {cam['fx']:g}, fy {cam['fy']:g}, cx {cam['cx']:g}, cy {cam['cy']:g} px{skew}")
    else:
        lines.append(f"  camera: {s(cam['model'])}")
    if "events" in d:
        e = d["events"]
        lines.append(
            f"  events: {e['count']:,} at {e['width']}×{e['height']}, {e['duration_s'] * 1000:.3f} ms, "
            f"{e['rate_ev_per_s'] / 1e6:.3f} M events/s"
        )
    if "event_sensor" in d:
        sensor = d["event_sensor"]

        def number(key: str, unit: str = "") -> str:
            return "unknown" if sensor[key] is None else f"{sensor[key]:g}{unit}"

        rule = s(sensor["refractory_rule"]) + ("" if sensor["refractory_rule_recorded"] else " (not recorded: the format's default)")
        lines.append(
            f"  event sensor: contrast +{number('contrast_pos')}/−{number('contrast_neg')}, "
            f"refractory {number('refractory_us', ' µs')}, {rule}"
        )
        rows = "; ".join(" ".join(f"{v:g}" for v in row) for row in sensor["event_to_frame"])
        assumed = "" if sensor["event_to_frame_recorded"] else " (not recorded: the same field of view assumed)"
        lines.append(f"  event→frame affine: [{rows}] (event pixel centres to frame pixels){assumed}")
    if "sensor_model" in d:
        m = d["sensor_model"]

        def figure(key: str, label: str, unit: str = "") -> str:
            return f"{label} {m[key]:g}{unit}" if m.get(key) else ""

        figures = [figure("contrast_sigma", "threshold σ"), figure("leak_hz", "leak", " Hz"),
                   figure("shot_noise_hz", "shot noise", " Hz (dark)"), figure("rate_spread_decades", "rate spread", " decades"),
                   f"hot pixels {100 * m['hot_pixel_fraction']:g} % at {m.get('hot_pixel_hz', 0):g} Hz" if m.get("hot_pixel_fraction") else "",
                   figure("full_well_e", "frame full well", " e⁻"), figure("read_noise_e", "read noise", " e⁻")]
        listed = ", ".join(x for x in figures if x) or "no noise"
        lines.append(f"  sensor model: {s(m['name'])} ({listed})")
    if "lights" in d:
        params = ", ".join(f"{s(k)}={s(v)}" for k, v in d["lights"]["params"].items())
        lines.append(f"  lights: {s(d['lights']['model'])}" + (f" ({params})" if params else ""))
    else:
        lines.append("  lights: none")
    lines.append("  ground truth: " + (", ".join(map(s, d["ground_truth"])) if d.get("ground_truth") else "none"))
    results = d["results"]
    lines.append(
        "  results: " + (", ".join(f"{s(k)} ({s(v['solver'])}, {v['seconds']:.2f} s)" for k, v in results.items()) or "none")
    )
    r = d["data_rate"]
    lines.append(
        f"  data rate: {100 * r['total']:.1f} % of 24 RGB frames per period "
        f"(frames {100 * r['frames']:.1f} %, events {100 * r['events']:.1f} %, {r['periods']:g} period(s))"
    )
    if "event_encoding" in d:
        e = d["event_encoding"]
        lines.append(
            f"  EVT 3.0: {e['evt3_bytes']:,} bytes ({e['bytes_per_event']:.2f} per event; 16-bit estimate "
            f"{e['estimate_bytes']:,}), data rate {100 * e['data_rate_total']:.1f} % "
            f"(events {100 * e['data_rate_events']:.1f} %)"
        )
    return "\n".join(lines)


@app.command()
def info(
    file: Path = typer.Argument(..., help="A hybrid-capture HDF5 file."),
    as_json: bool = typer.Option(False, "--json", help="Print the summary as JSON."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help=QUIET_HELP),
) -> None:
    """Show what a capture holds: resolution, frames and exposure, the camera model (with a perspective
    camera's focal lengths and principal point), events and rate, the event sensor's calibration
    (contrast thresholds, refractory period and rule, the event→frame affine), the sensor model a
    synthetic capture was made with (its noise figures), lights, ground truth,
    stored results, and the data rate against 24 RGB 8-bit frames."""
    with psfmt.read(file, verify=True) as capture:
        summary = describe(capture)
    echo(json.dumps(summary, indent=2) if as_json else _text(summary))
