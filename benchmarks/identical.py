"""Fingerprints of the simulator's captures and the solvers' results on the benchmark scenes, to show
that a change which should move or rename code alone changed no output.

For each scene of ``benchmarks/baselines.py`` (sphere, blobs, relief and the DiLiGenT shapes found
under ``--geometry-root``) at ``--size`` px: the direct hybrid capture (events at half the size,
C = 0.15, 2 ms reset-at-end), its 24-light classic twin and, with ``--semi``, the semi-real recipe
of ``benchmarks/dualres.py``. Recorded: SHA-256 of the event columns, of the frames and of the
ground truth; per solver (dualres, eventps, frameps on the three exposures, frameps robust on 24
lights) the MAE and the SHA-256 of the normal map.

``--compare OLD.json`` checks a new run against an old one: captures must be bit-identical; a solver
whose normal map differs in bits passes as float noise when its MAE moves by at most
``--tolerance-deg`` (the solvers use threaded BLAS and torch kernels whose summation order may vary
between runs), and the script exits 1 otherwise.

    git checkout OLD && python benchmarks/identical.py --out /tmp/before.json
    git checkout NEW && python benchmarks/identical.py --compare /tmp/before.json
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from baselines import GEOMETRY_ROOT, scenes
from dualres import DILIGENT_LIGHTS, SHINY
from results_io import write_results

import psfmt
from pstoolkit.evaluation.scoring import score
from pstoolkit.plugin.manager import get_registries
from pstoolkit.sim.config import SimulationConfig
from pstoolkit.sim.simulator import simulate
from pstoolkit.solve.base import run_solver
from pstoolkit_diligent.rendered import semi_real_from_capture

RESULTS = Path(__file__).resolve().parent / "results" / "identical.json"
SOLVERS: tuple[tuple[str, str, list[str]], ...] = (
    ("dualres", "hybrid", ["seed=0"]),
    ("eventps", "hybrid", []),
    ("frameps", "hybrid", []),
    ("frameps", "classic", ["robust=true"]),
)


def digest(*arrays: np.ndarray | None) -> str:
    """SHA-256 over the dtypes, shapes and bytes of ``arrays`` (None hashes as a marker)."""
    h = hashlib.sha256()
    for a in arrays:
        if a is None:
            h.update(b"none")
            continue
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def capture_prints(capture: psfmt.Capture) -> dict[str, str]:
    out: dict[str, str] = {}
    if capture.events is not None:
        ev = capture.events.read()
        out["events"] = digest(ev.x, ev.y, ev.t, ev.p)
    if capture.frames is not None:
        f = capture.frames
        out["frames"] = digest(np.asarray(f.data[:]), f.t_start_us, f.t_end_us, f.light_direction, f.light_intensity)
    gt = capture.ground_truth
    if gt is not None:
        out["ground_truth"] = digest(gt.normal, gt.mask, gt.albedo, gt.depth)
    return out


def solver_print(solver: str, capture: psfmt.Capture, assignments: list[str]) -> dict[str, Any]:
    """MAE and coverage as ``pstoolkit run`` scores them, and the normal map's digest."""
    entry = get_registries().solvers.get(solver)
    result, _ = run_solver(entry, capture, entry.parse_options(assignments))
    normal = np.where(result.mask[..., None], result.normal, np.float32(0.0)).astype(np.float32)
    scored = score(normal, capture.ground_truth)
    assert scored is not None
    return {"mae_deg": scored.stats["mae_deg"], "coverage": scored.stats["coverage"], "normal": digest(normal)}


def fingerprints(args: argparse.Namespace, folder: Path) -> dict[str, Any]:
    lights = str(args.diligent_lights) if args.diligent_lights.is_file() else "grid"
    out: dict[str, Any] = {}
    for label, scene, options in scenes(args.geometry_root):
        common: dict[str, Any] = {"scene": scene, "scene_options": options, "size": args.size, "seed": 0}
        kinds = {"direct": (folder / f"{label}-hybrid.h5", folder / f"{label}-classic.h5")}
        simulate(SimulationConfig(event_scale=0.5, **common), kinds["direct"][0])
        simulate(SimulationConfig(discrete_lights=24, **common), kinds["direct"][1])
        if args.semi:
            grid = folder / f"{label}-grid.h5"
            simulate(SimulationConfig(scene=scene, scene_options=[*options, *SHINY], size=args.size,
                                      seed=0, lights=lights, discrete_lights=96, bit_depth=16, auto_gain="peak"), grid)
            kinds["semi"] = (folder / f"{label}-semi.h5", folder / f"{label}-semi-classic.h5")
            semi_real_from_capture(grid, kinds["semi"][0], size=args.size, seed=0)
            semi_real_from_capture(grid, kinds["semi"][1], size=args.size, discrete_lights=24, seed=0)
        for kind, (hybrid_path, classic_path) in kinds.items():
            hybrid, classic = psfmt.load(hybrid_path), psfmt.load(classic_path)
            record: dict[str, Any] = {"hybrid": capture_prints(hybrid), "classic": capture_prints(classic)}
            for solver, which, assignments in SOLVERS:
                key = " ".join([solver, which, *assignments])
                record[key] = solver_print(solver, hybrid if which == "hybrid" else classic, assignments)
                print(f"  {kind:6s} {label:7s} {key:36s} {record[key]['mae_deg']:7.3f}°", flush=True)
            out[f"{kind} {label}"] = record
    return out


def compare(new: dict[str, Any], old: dict[str, Any], tolerance_deg: float) -> list[str]:
    """Lines naming every difference beyond the allowed float noise (empty: the same outputs)."""
    problems = []
    for name in sorted(set(old) | set(new)):
        if name not in old or name not in new:
            problems.append(f"{name}: only in {'the new run' if name in new else 'the old run'}")
            continue
        for key in sorted(set(old[name]) | set(new[name])):
            a, b = old[name].get(key), new[name].get(key)
            if key in ("hybrid", "classic"):
                if a != b:
                    problems.append(f"{name} {key} capture: {a} != {b}")
            elif a is None or b is None:
                problems.append(f"{name} {key}: missing in one run")
            elif a["normal"] != b["normal"]:
                moved = abs(a["mae_deg"] - b["mae_deg"])
                verdict = "float noise" if moved <= tolerance_deg else "DIFFERENT"
                print(f"{name} {key}: normals differ in bits, MAE {a['mae_deg']:.6f}° → {b['mae_deg']:.6f}° ({verdict})")
                if moved > tolerance_deg:
                    problems.append(f"{name} {key}: MAE {a['mae_deg']:.6f}° → {b['mae_deg']:.6f}°")
    return problems


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=64, help="frame size in pixels (default 64)")
    parser.add_argument("--semi", action="store_true", help="also the semi-real recipe")
    parser.add_argument("--geometry-root", type=Path, default=GEOMETRY_ROOT)
    parser.add_argument("--diligent-lights", type=Path, default=DILIGENT_LIGHTS)
    parser.add_argument("--compare", type=Path, help="an earlier run's JSON to check against")
    parser.add_argument("--tolerance-deg", type=float, default=1e-3)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        prints = fingerprints(args, Path(tmp))
    write_results(args.out, {"benchmark": "identical", "config": {"size": args.size, "semi": args.semi}, "captures": prints})
    print(f"wrote {args.out}")
    if args.compare:
        old = json.loads(args.compare.read_text())["captures"]
        problems = compare(prints, old, args.tolerance_deg)
        for line in problems:
            print(line)
        print("identical outputs" if not problems else f"{len(problems)} differences")
        sys.exit(1 if problems else 0)


if __name__ == "__main__":
    main()
