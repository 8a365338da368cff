"""Accuracy, coverage, time and data rate of the baseline solvers ``frameps`` and ``eventps``, and the
speed of ``eventps`` per time window.

For each scene — the simulator's ``sphere``, ``blobs`` and ``relief`` and the three DiLiGenT shapes
of ``/work/shared/data/diligent-geometry/`` through the ``geometry`` scene — two captures are
simulated with the scene's default materials (GGX, so highlights and shadows are present): a classic
one with 24 instantaneous lights evenly round the ring, and a hybrid one with 3 long exposures and
events at ``--event-scale`` of the frame resolution over ``--periods`` turns. Rows:

- ``frameps`` with 3, 6, 12 and 24 discrete lights (``frames=K`` of the 24, evenly spread),
- ``frameps robust`` with the 24 lights,
- ``frameps`` with the 3 long exposures (equivalent lights),
- ``eventps`` on the hybrid capture's events alone, and as the paper has it (``reweight=0``: plain
  least squares; ``fill=false``: pixels without their own fit left out).

Scores are those of ``pstoolkit run`` (``pstoolkit.evaluation.scoring.score``): MAE over the ground-truth
mask with an unsolved pixel counted as 90°, ``coverage`` (share of mask pixels solved) and
``mae_solved_deg`` (MAE over them). Data rate counts only the data the row uses (frames as 24-bit RGB,
events as 16-bit words; 100 % = 24 RGB frames per turn).

Speed (``--speed-size`` targets, Lambertian sphere, events at 0.5 and 1.0 of the target, data in
memory, median of ``--repeat`` runs, wall-clock and process CPU seconds, as the machine may be
shared; the load average is recorded):

- ``eventps.stream`` over ``--speed-turns`` turns in windows of one turn, each map resampled to the
  target (``resample.Resampler``), with windows fitted on 1 and on 2 threads: maps per second, the
  real-time figure (target ≥ 100 maps/s for 256² targets from 128² events on 2 cores);
- the solver with ``window_us=<period>`` (``pstoolkit run --set window_us=…``, threads = the cores) on
  the same capture: windows per solver second (it also fits the whole capture, from the same pairs);
- the solver on one turn of events: whole-capture maps per second.

Acceptance (printed and stored): coverage 100 % for eventps on every scene; eventps MAE within 2× of
frameps with 24 lights on every scene; ≥ 100 maps/s through the stream on 2 threads.

Prints the tables and writes ``benchmarks/results/baselines.json``.

    python benchmarks/baselines.py                      # 256×256 frames, 128×128 events
    python benchmarks/baselines.py --size 64 --speed-size 64 --repeat 3   # quick mode
    python benchmarks/baselines.py --speed-only        # the eventps speed alone
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from results_io import write_results

import psfmt
from pstoolkit._shared.progress import no_progress
from pstoolkit.evaluation.scoring import score
from pstoolkit.optics.lights import build_light_model
from pstoolkit.plugin.manager import get_registries
from pstoolkit.sim.config import SimulationConfig
from pstoolkit.sim.simulator import simulate
from pstoolkit.solve.base import run_solver
from pstoolkit_eventps import eventps
from pstoolkit_eventps.resample import Resampler

RESULTS = Path(__file__).resolve().parent / "results" / "baselines.json"
GEOMETRY_ROOT = Path("/work/shared/data/diligent-geometry")
GEOMETRY_OBJECTS = ("bear", "cat", "pot1")
LIGHT_COUNTS = (3, 6, 12, 24)
TARGET_MAPS_PER_S = 100.0
MAE_FACTOR = 2.0
"""eventps's MAE may be at most this multiple of frameps's with 24 lights."""
PAPER_EVENTPS = ["reweight=0", "fill=false"]
STREAM_THREADS = (1, 2)
"""Threads of the stream API measured: one core, and the two cores of the target machine."""
HYBRID_EVENT_SCALE = 0.5
"""The speed target is for events at half the target's resolution (128² events, 256² targets)."""


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


def run_row(solver: str, capture: psfmt.Capture, assignments: list[str], rate: float) -> dict[str, Any]:
    """One solver run scored as ``pstoolkit run`` scores it: MAE, median, coverage, MAE of the solved pixels."""
    entry = get_registries().solvers.get(solver)
    result, seconds = run_solver(entry, capture, entry.parse_options(assignments))
    scored = score(np.where(result.mask[..., None], result.normal, np.float32(0.0)), capture.ground_truth)
    assert scored is not None
    row = {"solver": solver, "options": " ".join(assignments), "seconds": seconds, "data_rate": rate}
    row.update({key: scored.stats[key] for key in ("mae_deg", "median_deg", "coverage", "mae_solved_deg")})
    return row


def scene_rows(label: str, scene: str, options: list[str], args: argparse.Namespace, folder: Path) -> list[dict[str, Any]]:
    common: dict[str, Any] = {"scene": scene, "scene_options": options, "size": args.size, "seed": args.seed}
    classic_path, hybrid_path = folder / f"{label}-classic.h5", folder / f"{label}-hybrid.h5"
    started = time.perf_counter()
    simulate(SimulationConfig(discrete_lights=max(LIGHT_COUNTS), **common), classic_path)
    simulate(SimulationConfig(event_scale=args.event_scale, periods=args.periods, **common), hybrid_path)
    print(f"{label}: simulated in {time.perf_counter() - started:.1f} s", flush=True)
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
    rows.append(run_row("eventps", events_only, PAPER_EVENTPS, rate.event_rate))
    names = [f"{k} lights" for k in LIGHT_COUNTS] + ["24 lights, robust", "3 long exposures"]
    names += [f"events {args.periods} turn(s)", f"events {args.periods} turn(s), paper"]
    for row, name in zip(rows, names):
        row.update(scene=label, input=name)
    return rows


def _timed(work: Any, repeat: int) -> tuple[float, float, float]:
    """Median wall and CPU seconds and best wall seconds of ``repeat`` calls of ``work`` (after one warm-up)."""
    work()
    wall, cpu = [], []
    for _ in range(repeat):
        start, start_cpu = time.perf_counter(), time.process_time()
        work()
        wall.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    return float(np.median(wall)), float(np.median(cpu)), float(min(wall))


def eventps_speed(size: int, event_scale: float, turns: int, repeat: int, folder: Path) -> dict[str, Any]:
    """Maps per second of ``eventps`` on a Lambertian sphere with a size×size target: windows of one turn
    through the stream API and through the solver, and the solver on one turn."""
    path = folder / f"speed-{event_scale:g}.h5"
    simulate(SimulationConfig(scene="sphere", size=size, brdf="lambertian", event_scale=event_scale, periods=turns), path)
    capture = psfmt.load(path)
    capture = psfmt.Capture(events=capture.events, lights=capture.lights, calibration=capture.calibration)
    events = capture.events
    assert events is not None and capture.lights is not None
    stream = events.read()
    light = build_light_model(capture.lights)
    period = float(light.period_us)
    cal = capture.calibration
    params = eventps.Params(contrast_pos=cal.contrast_pos, contrast_neg=cal.contrast_neg, refractory_us=cal.refractory_us)
    resample = Resampler(cal.event_to_frame, (events.height, events.width), (size, size))
    counted: list[int] = []

    def windows(threads: int) -> None:
        maps = 0
        for window in eventps.stream(
            stream.chunks(1 << 16), light, events.width, events.height, params, window_us=period, threads=threads
        ):
            resample.normals(window.normal, window.confidence > 0)
            resample.nearest(window.confidence)
            maps += 1
        counted.append(maps)

    rates: dict[str, Any] = {}
    for threads in STREAM_THREADS:
        wall, cpu, best = _timed(lambda threads=threads: windows(threads), repeat)
        maps = counted[-1]
        rates[f"stream_{threads}_threads"] = {"maps_per_s": maps / wall, "maps_per_cpu_s": maps / cpu, "best_maps_per_s": maps / best}
    entry = get_registries().solvers.get("eventps")
    solver = entry.obj()
    windowed = entry.parse_options([f"window_us={period:g}"])
    solver_wall, solver_cpu, _ = _timed(lambda: solver.solve(capture, windowed, no_progress), repeat)
    one_turn = psfmt.Capture(
        events=psfmt.Events(events.width, events.height, stream.window(0, int(period))), lights=capture.lights, calibration=cal
    )
    whole_wall, whole_cpu, _ = _timed(lambda: solver.solve(one_turn, entry.parse_options([]), no_progress), repeat)
    return {
        "target": f"{size}x{size}",
        "event_scale": event_scale,
        "events_size": f"{events.width}x{events.height}",
        "turns": turns,
        "events_per_turn": len(stream) / turns,
        "maps": counted[-1],
        **rates,
        "solver_windows_per_s": counted[-1] / solver_wall,
        "solver_windows_per_cpu_s": counted[-1] / solver_cpu,
        "whole_maps_per_s": 1.0 / whole_wall,
        "whole_maps_per_cpu_s": 1.0 / whole_cpu,
        "target_maps_per_s": TARGET_MAPS_PER_S,
    }


def print_table(rows: list[dict[str, Any]]) -> None:
    header = f"{'scene':<8} {'solver':<8} {'input':<26} {'MAE°':>7} {'coverage':>9} {'MAE° solved':>12} {'s':>7} {'rate %':>7}"
    print(header)
    print("-" * len(header))
    for r in rows:
        solved = "–" if r["mae_solved_deg"] is None else f"{r['mae_solved_deg']:.2f}"
        print(
            f"{r['scene']:<8} {r['solver']:<8} {r['input']:<26} {r['mae_deg']:7.2f} {100 * r['coverage']:8.1f}% "
            f"{solved:>12} {r['seconds']:7.3f} {100 * r['data_rate']:7.1f}"
        )


def acceptance(rows: list[dict[str, Any]], speed: list[dict[str, Any]], periods: int) -> dict[str, Any]:
    """Per scene eventps against frameps with 24 lights, and the verdicts (None without the rows)."""
    by = {(r["scene"], r["input"]): r for r in rows}
    labels = list(dict.fromkeys(r["scene"] for r in rows))
    scenes_out = {}
    for label in labels:
        event, frame = by[(label, f"events {periods} turn(s)")], by[(label, "24 lights")]
        scenes_out[label] = {
            "eventps_mae_deg": event["mae_deg"],
            "eventps_coverage": event["coverage"],
            "frameps_24_mae_deg": frame["mae_deg"],
            "ratio": event["mae_deg"] / frame["mae_deg"],
        }
    hybrid = next(s for s in speed if s["event_scale"] == HYBRID_EVENT_SCALE)
    rate = hybrid[f"stream_{max(STREAM_THREADS)}_threads"]["maps_per_s"]
    return {
        "scenes": scenes_out,
        "coverage_100_every_scene": all(s["eventps_coverage"] == 1.0 for s in scenes_out.values()) if rows else None,
        "mae_within_2x_of_frameps_24_every_scene": all(s["ratio"] <= MAE_FACTOR for s in scenes_out.values()) if rows else None,
        "windowed_maps_per_s": rate,
        "windowed_maps_per_s_at_least_100": rate >= TARGET_MAPS_PER_S,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=256, help="frame size in pixels (default 256)")
    parser.add_argument("--event-scale", type=float, default=0.5, help="event pixels per frame pixel (default 0.5)")
    parser.add_argument("--periods", type=int, default=1, help="turns of the ring light in the hybrid capture")
    parser.add_argument("--speed-size", type=int, default=256, help="target size of the eventps speed test (default 256)")
    parser.add_argument("--speed-turns", type=int, default=10, help="turns of the eventps speed capture (one map each)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--repeat", type=int, default=10, help="runs per speed measurement (median kept)")
    parser.add_argument("--geometry-root", type=Path, default=GEOMETRY_ROOT)
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--speed-only", action="store_true", help="measure the eventps speed only, no accuracy rows")
    args = parser.parse_args()

    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for label, scene, options in [] if args.speed_only else scenes(args.geometry_root):
            rows.extend(scene_rows(label, scene, options, args, folder))
        load_before = os.getloadavg()
        speed = [eventps_speed(args.speed_size, scale, args.speed_turns, args.repeat, folder) for scale in (HYBRID_EVENT_SCALE, 1.0)]
        load_after = os.getloadavg()
    print_table(rows)
    print()
    verdict = acceptance(rows, speed, args.periods)
    print(f"{'scene':<8} {'eventps MAE°':>13} {'coverage':>9} {'frameps 24 MAE°':>16} {'ratio':>6}")
    for label, s in verdict["scenes"].items():
        print(f"{label:<8} {s['eventps_mae_deg']:13.2f} {100 * s['eventps_coverage']:8.1f}% {s['frameps_24_mae_deg']:16.2f} {s['ratio']:6.2f}")
    print()
    for s in speed:
        streams = ", ".join(
            f"{threads} thread(s) {s[f'stream_{threads}_threads']['maps_per_s']:.1f} maps/s "
            f"({s[f'stream_{threads}_threads']['maps_per_cpu_s']:.1f} per CPU s)"
            for threads in STREAM_THREADS
        )
        print(
            f"eventps, {s['target']} target, {s['events_size']} events ({s['events_per_turn']:.0f} per turn, {s['turns']} turns, "
            f"one-turn windows): stream {streams}; solver --set window_us: {s['solver_windows_per_s']:.1f} windows/s "
            f"({s['solver_windows_per_cpu_s']:.1f} per CPU s); whole capture of one turn {s['whole_maps_per_s']:.1f} maps/s"
        )
    print(f"load average before/after the speed runs: {load_before[0]:.2f} / {load_after[0]:.2f} (1 min)")
    print(
        f"acceptance: coverage 100 % {verdict['coverage_100_every_scene']}, MAE ≤ {MAE_FACTOR:g}× frameps 24 "
        f"{verdict['mae_within_2x_of_frameps_24_every_scene']}, ≥ {TARGET_MAPS_PER_S:g} windowed maps/s "
        f"{verdict['windowed_maps_per_s_at_least_100']}"
    )
    result = {
        "benchmark": "baselines",
        "config": {"size": args.size, "event_scale": args.event_scale, "periods": args.periods, "seed": args.seed,
                   "repeat": args.repeat, "speed_size": args.speed_size, "speed_turns": args.speed_turns,
                   "speed_only": args.speed_only},
        "machine": {"python": platform.python_version(), "processor": platform.processor() or platform.machine(),
                    "cpus": os.cpu_count(), "load_average_1min": [load_before[0], load_after[0]]},
        "rows": rows,
        "eventps_speed": speed,
        "acceptance": verdict,
    }
    write_results(args.out, result)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
