"""Speed and accuracy of the registered normal integrators (``pstoolkit.surface``), on analytic
surfaces with exact normals (``pstoolkit.surface.shapes``), each integrator with its default options:

- seconds per 256² map, orthographic: a full frame of smooth waves (every pixel integrated) and the
  sphere below, median of ``--repeat`` runs after a warm-up, wall-clock and process CPU seconds (the
  machine may be shared: the load average is recorded);
- the sphere's depth error from its true normals at ``--size`` px (radius 0.45·size, its rim nearly
  grazing), orthographic and through a pinhole camera (focal length 1.04·size, a unit sphere 3 units
  away), after ``depth_error``'s least-squares scale and offset alignment, as a share of the
  diameter;
- the step: ``two_planes`` (two flat planes a quarter of the size apart, the step's lip a sixteenth
  high, its cliff invisible, the jump known through a ramp round a slit) — the planes' measured
  height difference as a share of the true jump: kept (near 1) or spread (well under 1).

Acceptance (printed and stored): every integrator's orthographic sphere within 0.5 % of the
diameter; ``poisson`` under 2 s per 256² map; ``bini`` keeps the step within 10 %.

Prints a table and writes ``benchmarks/results/integrate.json``.

    python benchmarks/integrate.py [--size 256] [--repeat 3]
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np
import scipy
from results_io import write_results

from pstoolkit.evaluation.metrics import depth_error
from pstoolkit.plugin.manager import get_registries
from pstoolkit.plugin.registry import Entry
from pstoolkit.surface.shapes import Synthetic, perspective_sphere, sphere, step_jump, two_planes

RESULTS = Path(__file__).resolve().parent / "results" / "integrate.json"
SPHERE_SHARE = 0.005
"""Acceptance: sphere depth RMSE at most this share of the diameter."""
POISSON_SECONDS = 2.0
STEP_SHARE = 0.1
"""Acceptance: bini's measured jump within this share of the true jump."""


def waves(size: int) -> Synthetic:
    """A full frame of smooth waves, z = 0.05·size·sin(2πu/λ)·cos(2πv/λ), λ = size/3, in pixels."""
    v, u = np.mgrid[0:size, 0:size].astype(np.float64)
    k, a = 2 * np.pi * 3 / size, 0.05 * size
    z = a * np.sin(k * u) * np.cos(k * v)
    du, dv = a * k * np.cos(k * u) * np.cos(k * v), -a * k * np.sin(k * u) * np.sin(k * v)
    normal = np.stack([-du, dv, np.ones_like(u)], axis=-1)  # ∝ (−∂z/∂u, ∂z/∂v, 1): y up, v down
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    return Synthetic(normal, z, np.ones((size, size), dtype=bool))


def timed(entry: Entry, shape: Synthetic, repeat: int) -> tuple[float, float]:
    """Median wall and CPU seconds of ``repeat`` integrations of ``shape`` (after one warm-up)."""
    options = entry.parse_options([])
    integrator = entry.obj()
    integrator.integrate(shape.normal, shape.mask, options, shape.camera)
    wall, cpu = [], []
    for _ in range(repeat):
        start, start_cpu = time.perf_counter(), time.process_time()
        integrator.integrate(shape.normal, shape.mask, options, shape.camera)
        wall.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    return float(np.median(wall)), float(np.median(cpu))


def sphere_share(entry: Entry, shape: Synthetic, diameter: float) -> float:
    """Depth RMSE after scale/offset alignment as a share of ``diameter``."""
    surface = entry.obj().integrate(shape.normal, shape.mask, entry.parse_options([]), shape.camera)
    return depth_error(surface.depth, shape.depth, shape.mask).rmse / diameter


def row(entry: Entry, size: int, repeat: int) -> dict[str, Any]:
    """Every figure of one integrator."""
    ortho, persp = sphere(size, 0.45 * size), perspective_sphere(size, focal=1.04 * size, distance=3.0, radius=1.0)
    jump = size / 4
    planes = two_planes(size, jump, lip=size / 16)
    step = entry.obj().integrate(planes.normal, planes.mask, entry.parse_options([]))
    waves_s, waves_cpu = timed(entry, waves(size), repeat)
    sphere_s, sphere_cpu = timed(entry, ortho, repeat)
    return {
        "integrator": entry.name,
        "plugin": entry.plugin,
        "options": entry.parse_options([]),
        "waves_s": waves_s,
        "waves_cpu_s": waves_cpu,
        "sphere_s": sphere_s,
        "sphere_cpu_s": sphere_cpu,
        "sphere_rmse_of_diameter": sphere_share(entry, ortho, 0.9 * size),
        "perspective_sphere_rmse_of_diameter": sphere_share(entry, persp, 2.0),
        "step_jump_share": step_jump(step.depth, size) / jump,
        "step_diagnostics": step.diagnostics,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    load_before = os.getloadavg()
    rows = [row(entry, args.size, args.repeat) for entry in get_registries().integrators]
    load_after = os.getloadavg()
    print(f"{'integrator':<12} {'waves s':>8} {'cpu s':>6} {'sphere s':>9} {'sphere err':>11} {'persp. err':>11} {'step kept':>10}")
    for r in rows:
        print(f"{r['integrator']:<12} {r['waves_s']:8.2f} {r['waves_cpu_s']:6.2f} {r['sphere_s']:9.2f} "
              f"{100 * r['sphere_rmse_of_diameter']:10.3f}% {100 * r['perspective_sphere_rmse_of_diameter']:10.3f}% "
              f"{100 * r['step_jump_share']:9.1f}%")
    by_name = {r["integrator"]: r for r in rows}
    acceptance = {
        "sphere_within_0_5_percent": all(r["sphere_rmse_of_diameter"] <= SPHERE_SHARE for r in rows),
        "poisson_under_2_s": "poisson" in by_name and by_name["poisson"]["waves_s"] < POISSON_SECONDS,
        "bini_keeps_the_step": "bini" in by_name and abs(by_name["bini"]["step_jump_share"] - 1) <= STEP_SHARE,
    }
    for name, met in acceptance.items():
        print(f"{name}: {'met' if met else 'MISSED'}")
    print(f"load average before/after: {load_before[0]:.2f} / {load_after[0]:.2f} (1 min)")
    result = {
        "machine": {"python": platform.python_version(), "numpy": np.__version__, "scipy": scipy.__version__,
                    "processor": platform.processor() or platform.machine(), "cpus": os.cpu_count(),
                    "load_average_1min": [load_before[0], load_after[0]]},
        "config": {"size": args.size, "repeat": args.repeat, "sphere_radius": 0.45 * args.size,
                   "perspective": {"focal": 1.04 * args.size, "distance": 3.0, "radius": 1.0},
                   "step": {"jump": args.size / 4, "lip": args.size / 16}},
        "rows": rows,
        "acceptance": acceptance,
    }
    write_results(RESULTS, result)
    print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
