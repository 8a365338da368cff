"""Depth from recovered normals on the benchmark scenes: how far the surface the registered
integrators (``poisson``, ``bini``) make of ``dualres``'s normals lies from the true depth, beside the
same from the true normals (the integrator's own error) and from the strongest frame baseline
(``frameps`` robust on 24 lights).

Scenes: the six of ``benchmarks/baselines.py`` (sphere, blobs, relief and the DiLiGenT shapes found
under ``--geometry-root``), simulated directly at ``--size`` px as ``benchmarks/dualres.py`` does
(hybrid capture with events at half the size, C = 0.15, 2 ms refractory; a 24-light classic twin).
The depth error is ``pstoolkit.evaluation.metrics.depth_error``: RMSE after the least-squares scale
and offset alignment over the pixels both the solver and the truth cover, given as a share of the
true depth range over them and of the object's size (the larger side of its mask's bounding box: a
sphere's diameter); the simulator's depth is in frame pixels, like the orthographic integrators'
output. A scene's true depth jumps where the shape occludes itself; no integrator of
normals alone sees those jumps, which sets the floor the ``truth`` rows show.

Prints a table and writes ``benchmarks/results/surfaces.json``.

    python benchmarks/surfaces.py [--size 128] [--scenes sphere bear]
"""

from __future__ import annotations

import argparse
import platform
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from baselines import GEOMETRY_ROOT, scenes
from results_io import write_results

import psfmt
from pstoolkit.evaluation.metrics import depth_error
from pstoolkit.plugin.manager import get_registries
from pstoolkit.sim.config import SimulationConfig
from pstoolkit.sim.simulator import simulate
from pstoolkit.solve.base import run_solver

RESULTS = Path(__file__).resolve().parent / "results" / "surfaces.json"
INTEGRATORS = ("poisson", "bini")


def normals_of(solver: str, capture: psfmt.Capture, assignments: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """A solver's normals (zero where it left a pixel out) and the pixels it solved."""
    entry = get_registries().solvers.get(solver)
    result, _ = run_solver(entry, capture, entry.parse_options(assignments))
    solved = result.mask & np.any(result.normal != 0, axis=-1) & np.isfinite(result.normal).all(axis=-1)
    return np.where(solved[..., None], result.normal, 0.0), solved


def depth_rows(label: str, source: str, normal: np.ndarray, mask: np.ndarray, truth: psfmt.GroundTruth) -> list[dict[str, Any]]:
    """One row per integrator: its depth error on ``normal`` over ``mask`` against the true depth."""
    rows = []
    for name in INTEGRATORS:
        entry = get_registries().integrators.get(name)
        surface = entry.obj().integrate(normal, mask, entry.parse_options([]))
        both = surface.mask & truth.mask & np.isfinite(truth.depth)
        error = depth_error(surface.depth, truth.depth, both)
        extent = float(np.ptp(truth.depth[both]))
        rows_px, cols_px = np.nonzero(truth.mask)
        size_px = float(max(np.ptp(rows_px), np.ptp(cols_px)) + 1)
        rows.append({"scene": label, "normals": source, "integrator": name, "rmse_px": error.rmse,
                     "rmse_of_range": error.rmse / extent, "rmse_of_size": error.rmse / size_px, "pixels": error.pixels,
                     "seconds": surface.seconds})
        print(f"  {label:7s} {source:22s} {name:8s} {100 * error.rmse / extent:6.2f} % of range, "
              f"{100 * error.rmse / size_px:5.2f} % of size ({error.rmse:6.3f} px) {surface.seconds:5.2f} s", flush=True)
    return rows


def scene_rows(label: str, scene: str, options: list[str], args: argparse.Namespace, folder: Path) -> list[dict[str, Any]]:
    common: dict[str, Any] = {"scene": scene, "scene_options": options, "size": args.size, "seed": args.seed}
    hybrid_path, classic_path = folder / f"{label}-hybrid.h5", folder / f"{label}-classic.h5"
    simulate(SimulationConfig(event_scale=0.5, **common), hybrid_path)
    simulate(SimulationConfig(discrete_lights=24, **common), classic_path)
    hybrid, classic = psfmt.load(hybrid_path), psfmt.load(classic_path)
    truth = hybrid.ground_truth
    rows = depth_rows(label, "truth", np.where(truth.mask[..., None], truth.normal, 0.0), truth.mask, truth)
    for source, solver, capture, assignments in (
        ("dualres", "dualres", hybrid, [f"seed={args.seed}"]),
        ("frameps 24 lights robust", "frameps", classic, ["robust=true"]),
    ):
        normal, solved = normals_of(solver, capture, assignments)
        rows += depth_rows(label, source, normal, solved & truth.mask, truth)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", type=int, default=128, help="frame size in pixels (default 128)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--scenes", nargs="*", help="labels to run (default: all found)")
    parser.add_argument("--geometry-root", type=Path, default=GEOMETRY_ROOT)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    started = time.perf_counter()
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        for label, scene, options in scenes(args.geometry_root):
            if args.scenes and label not in args.scenes:
                continue
            rows += scene_rows(label, scene, options, args, Path(tmp))
    print(f"\n{'scene':8s} {'normals':24s} " + " ".join(f"{name:>10s}" for name in INTEGRATORS) + "   (RMSE, % of the depth range)")
    for label in dict.fromkeys(r["scene"] for r in rows):
        for source in dict.fromkeys(r["normals"] for r in rows if r["scene"] == label):
            cells = [next(r for r in rows if r["scene"] == label and r["normals"] == source and r["integrator"] == name)
                     for name in INTEGRATORS]
            print(f"{label:8s} {source:24s} " + " ".join(f"{100 * c['rmse_of_range']:9.2f}%" for c in cells)
                  + "   size: " + " ".join(f"{100 * c['rmse_of_size']:5.2f}%" for c in cells))
    write_results(args.out, {
        "config": {"size": args.size, "seed": args.seed, "integrators": list(INTEGRATORS)},
        "machine": {"platform": platform.platform(), "python": platform.python_version()},
        "seconds": time.perf_counter() - started,
        "rows": rows,
    })
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
