"""Light calibration from a chrome sphere (``pstoolkit calibrate lights``): accuracy, and what it costs dualres.

Rows (``kind``):

- ``frames``: the simulator's ``chrome-sphere`` (8-bit) under DiLiGenT's 96 grid lights at each
  ``--sizes``, calibrated by ``sphere-frames`` from the capture (``orthographic``) and from its
  DiLiGenT-layout export (``folder``); the error is the angle to each true light.
- ``pinhole``: ``pstoolkit.testing.chrome_sphere_pinhole`` (an independent ray-traced highlight, 3°
  lobe) of a sphere off the optical axis through K (f = 1.25 frame widths) under 24 lights, its
  outline from the coverage mask; the error per light as above, and the orthographic reading of the
  same images for contrast.
- ``events``: the ``chrome-sphere`` under the ring (one turn, events at frame resolution) with
  refractory periods ``--refractory-us``, calibrated by ``sphere-events``; the error is the angle
  between the fitted and the true ring over 360 times of the turn (mean, max), with the fit's own
  residual and parameters.
- ``dualres``: the ``blobs`` scene at ``--dualres-size`` (default preset) solved by dualres with its
  true light model and with the ring calibrated from the events row at the largest size and the
  smallest refractory period (its period replaced by the capture's, as ``--store`` does): MAE of
  each, and their difference.

Prints the table and writes ``benchmarks/results/lightcal.json`` (``--out``).

    python benchmarks/lightcal.py                     # sizes 64 128, refractory 10 100 µs, dualres at 128
    python benchmarks/lightcal.py --sizes 64 --no-dualres
"""

from __future__ import annotations

import argparse
import platform
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from results_io import write_results

import psfmt
from pstoolkit.cli import main as cli
from pstoolkit.evaluation.scoring import score
from pstoolkit.hardware.highlight import highlight_direction
from pstoolkit.hardware.lightcal import keep_period
from pstoolkit.hardware.ringfit import angles_deg
from pstoolkit.hardware.sphere import SphereView, circle_from_mask
from pstoolkit.hardware.sphere_events import SphereEvents
from pstoolkit.hardware.sphere_frames import SphereFrames
from pstoolkit.optics.lights import RingLight
from pstoolkit.plugin.manager import get_registries
from pstoolkit.sim.config import SimulationConfig
from pstoolkit.sim.simulator import simulate
from pstoolkit.solve.base import run_solver
from pstoolkit.testing import chrome_sphere_pinhole

RESULTS = Path(__file__).resolve().parent / "results" / "lightcal.json"


def defaults(method: type) -> dict[str, Any]:
    return {o.name: o.default for o in method.options}


def error_row(kind: str, case: str, size: int, error: np.ndarray, seconds: float, **extra: Any) -> dict[str, Any]:
    return {"kind": kind, "case": case, "size": size, "mean_deg": float(error.mean()), "max_deg": float(error.max()),
            "seconds": seconds, **extra}


def frame_rows(data: Path, size: int) -> list[dict[str, Any]]:
    path = data / f"chrome-grid-{size}.h5"
    if not path.exists():
        simulate(SimulationConfig(scene="chrome-sphere", size=size, lights="grid"), path)
    folder = data / f"chrome-grid-{size}PNG"
    if not folder.exists():
        assert cli(["export", str(path), "--frames", "diligent", "-o", str(folder), "-q"]) == 0
    with psfmt.read(path) as capture:
        truth = np.asarray(capture.frames.light_direction)
    rows = []
    for case, source in (("orthographic", path), ("folder", folder)):
        start = time.perf_counter()
        fit = SphereFrames().calibrate(source, **defaults(SphereFrames))
        rows.append(error_row("frames", case, size, angles_deg(fit.directions, truth), time.perf_counter() - start))
    return rows


def pinhole_rows(size: int, seed: int) -> list[dict[str, Any]]:
    k = np.array([[1.25 * size, 0.0, (size - 1) / 2], [0.0, 1.25 * size, (size - 1) / 2], [0.0, 0.0, 1.0]])
    centre, radius = np.array([12.0, -6.0, -100.0]), 25.0
    mask = chrome_sphere_pinhole(k, centre, radius, np.array([0.0, 0.0, 1.0]), size, lobe_deg=None) > 0.5
    circle, outline = circle_from_mask(mask, "mask")
    rng = np.random.default_rng(seed)
    lights = rng.normal(size=(24, 3)) * np.array([0.5, 0.5, 0.0]) + np.array([0.0, 0.0, 1.0])
    lights /= np.linalg.norm(lights, axis=1, keepdims=True)
    rows = []
    for case, sphere in (("pinhole", SphereView.build(circle, k, outline)), ("pinhole read as orthographic", SphereView.build(circle))):
        start = time.perf_counter()
        found = np.array([highlight_direction(chrome_sphere_pinhole(k, centre, radius, light, size), sphere, 0.5) for light in lights])
        rows.append(error_row("frames", case, size, angles_deg(found, lights), time.perf_counter() - start))
    return rows


def ring_path(data: Path, size: int, refractory_us: float) -> Path:
    path = data / f"chrome-ring-{size}-r{refractory_us:g}.h5"
    if not path.exists():
        simulate(SimulationConfig(scene="chrome-sphere", size=size, event_scale=1.0, periods=1, refractory_us=refractory_us), path)
    return path


def event_row(data: Path, size: int, refractory_us: float) -> tuple[dict[str, Any], psfmt.LightSpec]:
    path = ring_path(data, size, refractory_us)
    start = time.perf_counter()
    fit = SphereEvents().calibrate(path, **defaults(SphereEvents))
    seconds = time.perf_counter() - start
    with psfmt.read(path) as capture:
        truth = RingLight.from_spec(capture.lights)
        events = len(capture.events)
    fitted = RingLight.from_spec(fit.spec)
    t = np.linspace(0.0, truth.period_us, 360, endpoint=False)
    error = angles_deg(fitted.evaluate(t)[0], truth.evaluate(t)[0])
    params = {k: fit.spec.params[k] for k in ("elevation_deg", "phase_deg", "period_us")}
    row = error_row("events", f"refractory {refractory_us:g} µs", size, error, seconds, residual_deg=fit.residual_deg,
                    windows=len(fit.times_us), events=events, **params)
    return row, fit.spec


def dualres_rows(data: Path, size: int, calibrated: psfmt.LightSpec) -> list[dict[str, Any]]:
    path = data / f"blobs-{size}-seed0.h5"
    if not path.exists():
        simulate(SimulationConfig(scene="blobs", size=size, seed=0), path)
    entry = get_registries().solvers.get("dualres")
    options = entry.parse_options([])
    rows = []
    with psfmt.read(path) as capture:
        for case, lights in (("true lights", capture.lights), ("calibrated lights", calibrated)):
            start = time.perf_counter()
            # the rig's period pulses time the frames: the stored model keeps their period (as --store does)
            result, _ = run_solver(entry, replace(capture, lights=keep_period(lights, capture.lights)), options)
            stats = score(result.normal, capture.ground_truth).stats
            rows.append({"kind": "dualres", "case": case, "size": size, "mae_deg": stats["mae_deg"],
                         "median_deg": stats["median_deg"], "seconds": time.perf_counter() - start})
    rows[1]["mae_minus_true_deg"] = rows[1]["mae_deg"] - rows[0]["mae_deg"]
    return rows


def show(row: dict[str, Any]) -> None:
    if row["kind"] == "dualres":
        extra = f"  MAE {row['mae_deg']:.3f}°, median {row['median_deg']:.3f}°"
        if "mae_minus_true_deg" in row:
            extra += f", {row['mae_minus_true_deg']:+.3f}° against true lights"
        print(f"{row['kind']:<8} {row['case']:<30} {row['size']:>5}{extra:<40} {row['seconds']:7.1f}", flush=True)
        return
    extra = ""
    if row["kind"] == "events":
        extra = f"  residual {row['residual_deg']:.2f}°, e {row['elevation_deg']:.2f}°, phase {row['phase_deg']:.2f}°"
    print(f"{row['kind']:<8} {row['case']:<30} {row['size']:>5} {row['mean_deg']:8.3f} {row['max_deg']:8.3f} {row['seconds']:7.1f}{extra}",
          flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="*", default=[64, 128])
    parser.add_argument("--refractory-us", type=float, nargs="*", default=[10.0, 100.0])
    parser.add_argument("--dualres-size", type=int, default=128)
    parser.add_argument("--no-dualres", action="store_true")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--data", type=Path, default=None, help="folder keeping the simulated captures")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    data = args.data or Path("benchmarks/results/data")
    data.mkdir(parents=True, exist_ok=True)
    print(f"{'kind':<8} {'case':<30} {'size':>5} {'mean °':>8} {'max °':>8} {'s':>7}")
    rows: list[dict[str, Any]] = []
    for size in args.sizes:
        for row in frame_rows(data, size) + pinhole_rows(size, args.seed):
            rows.append(row)
            show(row)
    calibrated = None
    for size in args.sizes:
        for refractory in args.refractory_us:
            row, spec = event_row(data, size, refractory)
            rows.append(row)
            show(row)
            if size == max(args.sizes) and refractory == min(args.refractory_us):
                calibrated = spec
    if not args.no_dualres and calibrated is not None:
        for row in dualres_rows(data, args.dualres_size, calibrated):
            rows.append(row)
            show(row)
    write_results(args.out, {
        "machine": {"python": platform.python_version(), "processor": platform.processor() or platform.machine()},
        "config": {"sizes": args.sizes, "refractory_us": args.refractory_us, "dualres_size": args.dualres_size, "seed": args.seed},
        "rows": rows,
    })
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
