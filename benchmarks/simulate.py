"""Speed and memory of the simulator (``pstoolkit simulate``).

Simulates one light period of a 256×256-frame / 128×128-event hybrid capture (three long exposures,
C = 0.15, the CLI's other defaults) of each scene into a temporary folder, and reports the seconds of
the whole ``simulate`` call (scene, rendering, events and frames in one pass, writing the HDF5 file),
the events per second of it, and — for the compiled engine (``pstoolkit.sim.ring_engine``, the CPU path) —
the seconds and events per second of the engine alone (events and exposure sums, no file); the best
of ``--repeat`` runs, as the machine may be shared. Peak memory: the process's peak resident size
(``resource.getrusage``, includes torch and the interpreter) and the peak of Python-tracked
allocations (``tracemalloc``, numpy arrays included, torch tensors not; measured in a separate run,
as tracing slows allocation). Threads: numba's (``NUMBA_NUM_THREADS``, default all cores). Freed
memory is kept for reuse, as the ``pstoolkit`` command keeps it (``pstoolkit._shared.allocator``; ``--no-keep``
leaves glibc's defaults); the first run of each scene is reported beside the best (the first scene's
also loads the compiled engine). Prints a table and writes ``benchmarks/results/simulate.json``.

Target: ≥ 5 M events/s.

    python benchmarks/simulate.py [--size 256] [--scenes sphere blobs] [--device cpu] [--sensor ideal|evk4|davis346]
                                  [--refractory-us 2000] [--refractory-rule reset-at-end|rate-limited] [--repeat 3]
                                  [--no-keep]

``--sensor`` picks the sensor preset (``pstoolkit.sim.sensor``; default ideal, C = 0.15 as the table
says), the refractory options override its fields.
"""

from __future__ import annotations

import argparse
import os
import platform
import resource
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path
from typing import Any

import numba
import numpy as np
import torch
from results_io import write_results

import psfmt
from psfmt import REFRACTORY_RULES
from pstoolkit._shared.allocator import keep_freed_memory
from pstoolkit.plugin.manager import get_registries
from pstoolkit.sim import ring_engine
from pstoolkit.sim.config import SimulationConfig
from pstoolkit.sim.sensor import SENSOR_PRESETS
from pstoolkit.sim.simulator import build_renderer, build_scene, compiled_blocks, simulate

RESULTS = Path(__file__).resolve().parent / "results" / "simulate.json"
TARGET_EVENTS_PER_S = 5e6


def run_scene(config: SimulationConfig, folder: Path) -> dict[str, Any]:
    start = time.perf_counter()
    cpu = time.process_time()
    summary = simulate(config, folder / f"{config.scene}.h5")
    total = time.perf_counter() - start
    cpu = time.process_time() - cpu
    engine = float("nan")
    renderer = build_renderer(config, build_scene(config), get_registries().brdfs.get(config.brdf).obj())
    if ring_engine.supported(renderer):
        start = time.perf_counter()
        for _ in compiled_blocks(config, renderer):
            pass
        engine = time.perf_counter() - start
    with psfmt.read(summary.path) as capture:
        file_mb = summary.path.stat().st_size / 1e6
        rate = psfmt.data_rate(capture).rate
    return {
        "scene": config.scene,
        "events": summary.events,
        "seconds": total,
        "cpu_seconds": cpu,
        "events_per_s": summary.events / total,
        "engine_seconds": engine,
        "engine_events_per_s": summary.events / engine,
        "file_mb": file_mb,
        "data_rate": rate,
    }


def traced_peak_mb(config: SimulationConfig, folder: Path) -> float:
    tracemalloc.start()
    simulate(config, folder / f"{config.scene}-traced.h5")
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return peak / 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--scenes", nargs="+", default=["sphere", "blobs", "relief"])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--sensor", default="ideal", choices=tuple(SENSOR_PRESETS))
    parser.add_argument("--refractory-us", type=float, default=None, help="default: the preset's")
    parser.add_argument("--refractory-rule", default=None, choices=REFRACTORY_RULES, help="default: the preset's")
    parser.add_argument("--repeat", type=int, default=1, help="runs per scene; the fastest is kept")
    parser.add_argument("--no-keep", action="store_true",
                        help="leave glibc's allocator defaults (see pstoolkit._shared.allocator)")
    args = parser.parse_args()
    kept = False if args.no_keep else keep_freed_memory()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for scene in args.scenes:
            config = SimulationConfig.with_preset(
                args.sensor, scene=scene, size=args.size, event_scale=0.5, frames=3, periods=1,
                refractory_us=args.refractory_us, refractory_rule=args.refractory_rule, device=args.device,
            )
            runs = [run_scene(config, Path(tmp)) for _ in range(max(1, args.repeat))]
            best = min(runs, key=lambda r: r["seconds"])
            best["first_seconds"] = runs[0]["seconds"]
            best["engine_seconds"] = min(r["engine_seconds"] for r in runs)
            best["engine_events_per_s"] = best["events"] / best["engine_seconds"]
            best["traced_peak_mb"] = traced_peak_mb(config, Path(tmp))
            rows.append(best)
    peak_rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    print(f"{args.size}×{args.size} frames, {args.size // 2}×{args.size // 2} events, one period, sensor {args.sensor}, "
          f"C = {config.contrast:g}/{config.c_neg:g}, refractory {config.refractory_us:g} µs ({config.refractory_rule}), "
          f"device {args.device}, {numba.get_num_threads()} numba threads, "
          f"freed memory {'kept' if kept else 'returned'}")
    print(f"{'scene':8s} {'events':>9s} {'total s':>8s} {'first s':>8s} {'CPU s':>7s} {'M ev/s':>7s} {'engine s':>9s} "
          f"{'engine M ev/s':>14s} {'traced MB':>10s} {'rate %':>7s}")
    for r in rows:
        print(f"{r['scene']:8s} {r['events']:9,d} {r['seconds']:8.3f} {r['first_seconds']:8.3f} "
              f"{r['cpu_seconds']:7.2f} "
              f"{r['events_per_s'] / 1e6:7.3f} {r['engine_seconds']:9.3f} {r['engine_events_per_s'] / 1e6:14.3f} "
              f"{r['traced_peak_mb']:10.1f} {100 * r['data_rate']:7.1f}")
    best = max(r["events_per_s"] for r in rows)
    print(f"peak resident memory {peak_rss_mb:.0f} MB")
    print(f"target ≥ {TARGET_EVENTS_PER_S / 1e6:.0f} M events/s: best {best / 1e6:.3f} M events/s end to end "
          f"({'met' if best >= TARGET_EVENTS_PER_S else 'NOT met'}), "
          f"engine best {max(r['engine_events_per_s'] for r in rows) / 1e6:.3f} M events/s")
    result = {
        "size": args.size,
        "event_size": args.size // 2,
        "sensor": args.sensor,
        "refractory_us": config.refractory_us,
        "refractory_rule": config.refractory_rule,
        "repeat": args.repeat,
        "freed_memory_kept": kept,
        "device": args.device,
        "numba_threads": numba.get_num_threads(),
        "rows": rows,
        "peak_rss_mb": peak_rss_mb,
        "target_events_per_s": TARGET_EVENTS_PER_S,
        "machine": {"python": platform.python_version(), "numpy": np.__version__, "torch": torch.__version__,
                    "cpus": os.cpu_count(), "processor": platform.processor() or platform.machine(),
                    "argv": sys.argv[1:]},
    }
    write_results(RESULTS, result)
    print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
