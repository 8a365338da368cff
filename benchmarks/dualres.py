"""Acceptance table of the ``dualres`` solver (DualResPS) against the baselines, and its ablations.

Scenes: the simulator's ``sphere``, ``blobs`` (cast shadows) and a specular ``relief`` (F0 0.1,
roughness 0.25), and the DiLiGenT shapes of ``--geometry-root`` through the ``geometry`` scene, all
with GGX materials. Each scene is simulated twice with the same seed: a hybrid capture (``--size``
frames, events at ``--event-scale``, C = 0.15, three long exposures per period) and a classic one
with 24 instantaneous lights. Rows per scene:

- ``dualres`` fast (the default preset) on the hybrid capture,
- ``dualres paper`` (``--paper-epochs``, 0 skips it) and, beside it, ``dualres fast`` again, both on a
  hybrid capture of ``--paper-size`` (default ``--size``): the paper's MLP costs hours per 256 px
  object on a 2-core CPU, so it can be compared with fast at a smaller size,
- ``frameps`` on the same three long exposures, ``eventps`` on the same events,
- ``frameps`` with 24 discrete lights.

Acceptance: dualres MAE below frameps (3 frames) and eventps on every scene, below frameps with 24
lights on average; fast ≤ 90 s per 256×256 object on a 2-core CPU, within 0.3° of paper on average
(at the paper size), with the compute ratio paper : fast in seconds.

Ablations (``--ablation``): no cast-shadow mask; specular models sg, mlp, metallic; K = 4, 6, 9
frames per period (K = 3 is the main row). MAE is over the ground-truth mask with pixels a solver
leaves out counted as 90° (as ``pstoolkit run`` does). Data rate counts what each row reads.

Prints tables and writes ``benchmarks/results/dualres.json``.

    python benchmarks/dualres.py --ablation                     # the full table (256 px, paper 1200 epochs)
    python benchmarks/dualres.py --paper-size 64 --threads 1    # 256 px rows, paper against fast at 64 px
    python benchmarks/dualres.py --size 64 --scenes sphere blobs relief --paper-epochs 100 --ablation   # quick
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from baselines import GEOMETRY_ROOT, run_row, scenes
from results_io import write_results

import psfmt
from pstoolkit.simulator import SimulationConfig, simulate

RESULTS = Path(__file__).resolve().parent / "results" / "dualres.json"
SPECULAR_RELIEF = ["f0=0.1", "roughness=0.25"]
ABLATION_FRAMES = (4, 6, 9)
ABLATION_SPECULAR = ("sg", "mlp", "metallic")
FAST_LIMIT_S = 90.0
PAPER_MARGIN_DEG = 0.3


def _simulate(label: str, scene: str, options: list[str], args: argparse.Namespace, folder: Path, size: int | None = None,
              **extra: Any) -> psfmt.Capture:
    size = size or args.size
    path = folder / f"{label}-{size}-{'-'.join(f'{k}{v}' for k, v in extra.items()) or 'hybrid'}.h5"
    if not path.exists():
        simulate(SimulationConfig(scene=scene, scene_options=options, size=size, seed=args.seed,
                                  event_scale=args.event_scale, **extra), path)
    return psfmt.load(path)


def scene_rows(label: str, scene: str, options: list[str], args: argparse.Namespace, folder: Path) -> list[dict[str, Any]]:
    started = time.perf_counter()
    hybrid = _simulate(label, scene, options, args, folder)
    classic = _simulate(label, scene, options, args, folder, discrete_lights=24)
    print(f"{label}: simulated in {time.perf_counter() - started:.1f} s", flush=True)
    rate = psfmt.data_rate(hybrid)
    events_only = psfmt.Capture(events=hybrid.events, lights=hybrid.lights, calibration=hybrid.calibration,
                                ground_truth=hybrid.ground_truth)
    runs = [("dualres fast", "dualres", hybrid, [f"seed={args.seed}"], rate.rate)]
    if args.paper_epochs:
        small = hybrid if args.paper_size == args.size else _simulate(label, scene, options, args, folder, size=args.paper_size)
        small_rate = psfmt.data_rate(small).rate
        paper = ["preset=paper", f"epochs={args.paper_epochs}", f"seed={args.seed}"]
        if small is not hybrid:
            runs.append((f"dualres fast {args.paper_size} px", "dualres", small, [f"seed={args.seed}"], small_rate))
        runs.append((f"dualres paper {args.paper_size} px", "dualres", small, paper, small_rate))
    runs += [
        ("frameps 3 exposures", "frameps", hybrid, [], rate.frame_rate),
        ("eventps", "eventps", events_only, [], rate.event_rate),
        ("frameps 24 lights", "frameps", classic, [], 1.0),
    ]
    rows = []
    for name, solver, capture, assignments, data_rate in runs:
        row = run_row(solver, capture, assignments, data_rate)
        row.update(scene=label, method=name, events=len(hybrid.events))
        rows.append(row)
        print(f"  {name:<20} {row['mae_deg']:6.2f}° {row['seconds']:7.1f} s", flush=True)
    return rows


def ablation_rows(label: str, scene: str, options: list[str], args: argparse.Namespace, folder: Path) -> list[dict[str, Any]]:
    hybrid = _simulate(label, scene, options, args, folder)
    rate = psfmt.data_rate(hybrid).rate
    variants: list[tuple[str, psfmt.Capture, list[str], float]] = [("no cast-shadow mask", hybrid, ["shadows=false"], rate)]
    variants += [(f"specular {s}", hybrid, [f"specular={s}"], rate) for s in ABLATION_SPECULAR]
    for k in ABLATION_FRAMES:
        capture = _simulate(label, scene, options, args, folder, frames=k)
        variants.append((f"K = {k}", capture, [], psfmt.data_rate(capture).rate))
    rows = []
    for name, capture, assignments, data_rate in variants:
        row = run_row("dualres", capture, [*assignments, f"seed={args.seed}"], data_rate)
        row.update(scene=label, method=name)
        rows.append(row)
        print(f"  {name:<20} {row['mae_deg']:6.2f}° {row['seconds']:7.1f} s", flush=True)
    return rows


def table(rows: list[dict[str, Any]], title: str) -> None:
    labels = list(dict.fromkeys(r["scene"] for r in rows))
    methods = list(dict.fromkeys(r["method"] for r in rows))
    cell = {(r["scene"], r["method"]): r for r in rows}
    print(f"\n{title}: MAE° (seconds) [data rate %]")
    print(f"{'method':<22}" + "".join(f"{s:>20}" for s in labels) + f"{'average':>10}")
    for m in methods:
        values = [cell[(s, m)] for s in labels if (s, m) in cell]
        text = "".join(
            f"{c['mae_deg']:7.2f} ({c['seconds']:5.1f}) [{100 * c['data_rate']:4.1f}]" if c else f"{'':>20}"
            for c in (cell.get((s, m)) for s in labels)
        )
        print(f"{m:<22}{text}{np.mean([v['mae_deg'] for v in values]):10.2f}")


def verdict(rows: list[dict[str, Any]], size: int, paper_size: int) -> dict[str, Any]:
    """The acceptance criteria, each True/False (None when its rows are missing)."""
    by = {(r["scene"], r["method"]): r for r in rows}
    labels = list(dict.fromkeys(r["scene"] for r in rows))

    def mae(scene: str, method: str) -> float | None:
        row = by.get((scene, method))
        return None if row is None else row["mae_deg"]

    fast = [mae(s, "dualres fast") for s in labels]
    result: dict[str, Any] = {
        "below_frameps_3_every_scene": all(f < mae(s, "frameps 3 exposures") for s, f in zip(labels, fast)),
        "below_eventps_every_scene": all(f < mae(s, "eventps") for s, f in zip(labels, fast)),
        "below_frameps_24_on_average": float(np.mean(fast)) < float(np.mean([mae(s, "frameps 24 lights") for s in labels])),
        "fast_max_seconds": max(by[(s, "dualres fast")]["seconds"] for s in labels),
    }
    result["fast_within_limit"] = result["fast_max_seconds"] <= FAST_LIMIT_S if size == 256 else None
    paper_method = f"dualres paper {paper_size} px"
    fast_method = "dualres fast" if paper_size == size else f"dualres fast {paper_size} px"
    paper_rows = [by.get((s, paper_method)) for s in labels]
    if labels and all(paper_rows):
        fast_rows = [by[(s, fast_method)] for s in labels]
        result["paper_size"] = paper_size
        result["fast_minus_paper_deg"] = float(np.mean([f["mae_deg"] - p["mae_deg"] for f, p in zip(fast_rows, paper_rows)]))
        result["fast_within_0.3_of_paper"] = result["fast_minus_paper_deg"] <= PAPER_MARGIN_DEG
        result["paper_to_fast_seconds"] = float(sum(p["seconds"] for p in paper_rows) / sum(f["seconds"] for f in fast_rows))
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=256, help="frame size in pixels (default 256)")
    parser.add_argument("--event-scale", type=float, default=0.5, help="event pixels per frame pixel (default 0.5)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--paper-epochs", type=int, default=1200, help="epochs of the paper preset (0 = skip it)")
    parser.add_argument("--paper-size", type=int, default=0, help="frame size of the paper rows (default: --size)")
    parser.add_argument("--threads", type=int, default=0, help="torch CPU threads (default: torch's choice)")
    parser.add_argument("--scenes", nargs="*", help="labels to run (default: all found)")
    parser.add_argument("--ablation", action="store_true", help="also run the ablation table")
    parser.add_argument("--geometry-root", type=Path, default=GEOMETRY_ROOT)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    args.paper_size = args.paper_size or args.size
    if args.threads:
        torch.set_num_threads(args.threads)

    chosen = []
    for label, scene, options in scenes(args.geometry_root):
        if args.scenes and label not in args.scenes:
            continue
        chosen.append((label, scene, SPECULAR_RELIEF if label == "relief" else options))
    rows: list[dict[str, Any]] = []
    ablation: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for label, scene, options in chosen:
            rows.extend(scene_rows(label, scene, options, args, folder))
        if args.ablation:
            for label, scene, options in chosen:
                print(f"{label}: ablation", flush=True)
                ablation.extend(ablation_rows(label, scene, options, args, folder))
    table(rows, f"Accuracy, {args.size} px frames, events at {args.event_scale:g}")
    if ablation:
        main_rows = [dict(r, method="proposed (fast)") for r in rows if r["method"] == "dualres fast"]
        table(main_rows + ablation, "Ablation of dualres fast")
    checks = verdict(rows, args.size, args.paper_size)
    print("\nacceptance:", json.dumps(checks))
    result = {
        "benchmark": "dualres",
        "config": {"size": args.size, "event_scale": args.event_scale, "seed": args.seed,
                   "paper_epochs": args.paper_epochs, "paper_size": args.paper_size, "contrast": 0.15,
                   "frames_per_period": 3},
        "machine": {"python": platform.python_version(), "processor": platform.processor() or platform.machine(),
                    "torch_threads": torch.get_num_threads()},
        "rows": rows,
        "ablation": ablation,
        "acceptance": checks,
    }
    write_results(args.out, result)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
