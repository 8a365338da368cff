"""Accuracy, time and data rate of the baseline solvers ``frameps`` and ``eventps``.

For each scene — the simulator's ``sphere``, ``blobs`` and ``relief`` and the three DiLiGenT shapes
of ``/work/shared/data/diligent-geometry/`` through the ``geometry`` scene — two captures are
simulated with the scene's default materials (GGX, so highlights and shadows are present): a classic
one with 24 instantaneous lights evenly round the ring, and a hybrid one with 3 long exposures and
events at ``--event-scale`` of the frame resolution over ``--periods`` turns. Rows:

- ``frameps`` with 3, 6, 12 and 24 discrete lights (``frames=K`` of the 24, evenly spread),
- ``frameps robust`` with the 24 lights,
- ``frameps`` with the 3 long exposures (equivalent lights),
- ``eventps`` on the hybrid capture's events alone.

MAE is over the ground-truth mask, a pixel the solver leaves out counting as 90° (as ``pstoolkit
run`` does); ``covered`` is the share of mask pixels the solver did estimate, and ``mae_covered``
the MAE over them. Data rate counts only the data the row uses (frames as 24-bit RGB, events as
16-bit words; 100 % = 24 RGB frames per turn).

Speed: ``eventps`` normal maps per second from one turn of events of a Lambertian sphere with a
256×256 target, events at 128×128 (the hybrid layout) and at 256×256, median of ``--repeat`` solves
on data in memory. Target: ≥ 30 maps/s.

Prints a table and writes ``benchmarks/results/baselines.json``.

    python benchmarks/baselines.py                      # 256×256 frames, 128×128 events
    python benchmarks/baselines.py --size 64 --speed-size 64 --repeat 3   # quick mode
"""

from __future__ import annotations

import argparse
import platform
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

import psfmt
from pstoolkit.metrics import angular_error_deg
from pstoolkit.plugins import get_registries
from pstoolkit.simulator import SimulationConfig, simulate
from pstoolkit.solver import no_progress, run_solver
from results_io import write_results

RESULTS = Path(__file__).resolve().parent / "results" / "baselines.json"
GEOMETRY_ROOT = Path("/work/shared/data/diligent-geometry")
GEOMETRY_OBJECTS = ("bear", "cat", "pot1")
LIGHT_COUNTS = (3, 6, 12, 24)
TARGET_MAPS_PER_S = 30.0


def scenes(geometry_root: Path) -> list[tuple[str, str, list[str]]]:
    """(label, scene, scene options) of every benchmark scene whose data is present."""
    found = [("sphere", "sphere", []), ("blobs", "blobs", []), ("relief", "relief", [])]
    for name in GEOMETRY_OBJECTS:
        folder = geometry_root / name
        if folder.is_dir():
            found.append((name, "geometry", [f"source={folder}"]))
        else:
            print(f"skipping {name}: {folder} not found")
    return found


def accuracy(normal: np.ndarray, mask: np.ndarray, gt: psfmt.GroundTruth) -> dict[str, float]:
    errors = angular_error_deg(normal, gt.normal, gt.mask)
    covered = mask & gt.mask
    return {
        "mae_deg": float(np.where(mask, errors, 90.0)[gt.mask].mean()),
        "covered": float(covered.sum() / gt.mask.sum()),
        "mae_covered_deg": float(errors[covered].mean()) if covered.any() else float("nan"),
    }


def run_row(solver: str, capture: psfmt.Capture, assignments: list[str], rate: float) -> dict[str, Any]:
    entry = get_registries().solvers.get(solver)
    result, seconds = run_solver(entry, capture, entry.parse_options(assignments))
    assert capture.ground_truth is not None
    row = {"solver": solver, "options": " ".join(assignments), "seconds": seconds, "data_rate": rate}
    row.update(accuracy(result.normal, result.mask, capture.ground_truth))
    return row


def scene_rows(label: str, scene: str, options: list[str], args: argparse.Namespace, folder: Path) -> list[dict[str, Any]]:
    common: dict[str, Any] = {"scene": scene, "scene_options": options, "size": args.size, "seed": args.seed}
    classic_path, hybrid_path = folder / f"{label}-classic.h5", folder / f"{label}-hybrid.h5"
    started = time.perf_counter()
    simulate(SimulationConfig(discrete_lights=max(LIGHT_COUNTS), **common), classic_path)
    simulate(SimulationConfig(event_scale=args.event_scale, periods=args.periods, **common), hybrid_path)
    print(f"{label}: simulated in {time.perf_counter() - started:.1f} s")
    rows = []
    classic = psfmt.load(classic_path)
    for k in LIGHT_COUNTS:
        rows.append(run_row("frameps", classic, [f"frames={k}"], k / 24))
    rows.append(run_row("frameps", classic, ["robust=true"], max(LIGHT_COUNTS) / 24))
    hybrid = psfmt.load(hybrid_path)
    rate = psfmt.data_rate(hybrid)
    rows.append(run_row("frameps", hybrid, [], rate.frame_rate))
    events_only = psfmt.Capture(
        events=hybrid.events, lights=hybrid.lights, calibration=hybrid.calibration, ground_truth=hybrid.ground_truth
    )
    rows.append(run_row("eventps", events_only, [], rate.event_rate))
    names = [f"{k} lights" for k in LIGHT_COUNTS] + ["24 lights, robust", "3 long exposures", f"events {args.periods} turn(s)"]
    for row, name in zip(rows, names):
        row.update(scene=label, input=name)
    return rows


def eventps_speed(size: int, event_scale: float, repeat: int, folder: Path) -> dict[str, Any]:
    """Maps per second of ``eventps`` from one turn of a Lambertian sphere's events, size×size target."""
    path = folder / f"speed-{event_scale:g}.h5"
    simulate(SimulationConfig(scene="sphere", size=size, brdf="lambertian", event_scale=event_scale), path)
    capture = psfmt.load(path)
    capture = psfmt.Capture(events=capture.events, lights=capture.lights, calibration=capture.calibration,
                            ground_truth=capture.ground_truth)
    entry = get_registries().solvers.get("eventps")
    solver = entry.obj()
    options = entry.parse_options([])
    solver.solve(capture, options, no_progress)  # warm caches and imports
    seconds = []
    for _ in range(repeat):
        start = time.perf_counter()
        solver.solve(capture, options, no_progress)
        seconds.append(time.perf_counter() - start)
    median = float(np.median(seconds))
    assert capture.events is not None
    return {
        "target": f"{size}x{size}",
        "events_size": f"{capture.events.width}x{capture.events.height}",
        "events": len(capture.events),
        "median_s": median,
        "best_s": float(min(seconds)),
        "maps_per_s": 1.0 / median,
        "target_maps_per_s": TARGET_MAPS_PER_S,
    }


def print_table(rows: list[dict[str, Any]]) -> None:
    header = f"{'scene':<8} {'solver':<8} {'input':<22} {'MAE°':>7} {'covered':>8} {'MAE° cov':>9} {'s':>7} {'rate %':>7}"
    print(header)
    print("-" * len(header))
    for r in rows:
        print(
            f"{r['scene']:<8} {r['solver']:<8} {r['input']:<22} {r['mae_deg']:7.2f} {100 * r['covered']:7.1f}% "
            f"{r['mae_covered_deg']:9.2f} {r['seconds']:7.3f} {100 * r['data_rate']:7.1f}"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=256, help="frame size in pixels (default 256)")
    parser.add_argument("--event-scale", type=float, default=0.5, help="event pixels per frame pixel (default 0.5)")
    parser.add_argument("--periods", type=int, default=1, help="turns of the ring light in the hybrid capture")
    parser.add_argument("--speed-size", type=int, default=256, help="target size of the eventps speed test (default 256)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--repeat", type=int, default=20, help="solves per speed measurement (median kept)")
    parser.add_argument("--geometry-root", type=Path, default=GEOMETRY_ROOT)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()

    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for label, scene, options in scenes(args.geometry_root):
            rows.extend(scene_rows(label, scene, options, args, folder))
        speed = [eventps_speed(args.speed_size, scale, args.repeat, folder) for scale in (0.5, 1.0)]
    print_table(rows)
    print()
    for s in speed:
        print(
            f"eventps speed, {s['target']} target, {s['events_size']} events ({s['events']} per turn): "
            f"{s['maps_per_s']:.1f} maps/s (median {1000 * s['median_s']:.1f} ms, best {1000 * s['best_s']:.1f} ms; "
            f"target ≥ {TARGET_MAPS_PER_S:g})"
        )
    result = {
        "benchmark": "baselines",
        "config": {"size": args.size, "event_scale": args.event_scale, "periods": args.periods, "seed": args.seed,
                   "repeat": args.repeat, "speed_size": args.speed_size},
        "machine": {"python": platform.python_version(), "processor": platform.processor() or platform.machine()},
        "rows": rows,
        "eventps_speed": speed,
    }
    write_results(args.out, result)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
