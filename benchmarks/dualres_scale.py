"""How the ``dualres`` solver's time and memory grow with the capture's resolution (issue 26).

For each ``--sizes`` N: the simulator's ``blobs`` scene at N² frame pixels (events at half that per
axis, the defaults of ``pstoolkit simulate``), kept in ``--data`` between runs, solved by ``dualres``
with its default preset in a child process, so that the peak resident memory is the solve's own (the
child's VmHWM, read from /proc as tests/psfmt/test_fuzz.py does: ru_maxrss of a child carries the
parent's size over the fork). Per size: solve seconds, microseconds per frame pixel, peak memory,
MAE, and the wall seconds of the solver's stages (``diagnostics["seconds"]``: preprocess, detect,
closed_form, problem, field, train_<stage>, redetect_<stage>, output; preprocessing's own split under
``preprocess_split``).

Acceptance (printed, stored in the JSON; a criterion whose size was not run is None): time per pixel
at 1024² within 1.3× of 256²; 1024² solved in at most 120 s; peak memory at 1024² at most 3 GB.
Seconds are wall seconds on this machine with torch's threads (``--threads``, default: torch's
choice).

Prints the table and writes ``benchmarks/results/dualres_scale.json`` (``--out``).

    python benchmarks/dualres_scale.py                          # 256, 512, 1024
    python benchmarks/dualres_scale.py --sizes 256 512 --data /tmp/blobs
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

from results_io import write_results

RESULTS = Path(__file__).resolve().parent / "results" / "dualres_scale.json"
SIZES = (256, 512, 1024)
PER_PIXEL_RATIO = 1.3
TIME_LIMIT_S = 120.0
MEMORY_LIMIT_GB = 3.0
LARGE = 1024
SMALL = 256

# The child: solve one capture, print one JSON line with the solve's numbers and its own peak memory.
CHILD = """
import json, sys, time
import numpy as np
import psfmt
import torch
from pstoolkit.evaluation.scoring import score
from pstoolkit.plugin.manager import get_registries

path, threads, assignments = sys.argv[1], int(sys.argv[2]), sys.argv[3:]
if threads:
    torch.set_num_threads(threads)
capture = psfmt.load(path)
entry = get_registries().solvers.get("dualres")
solver = entry.obj(device="cpu")
options = entry.parse_options(assignments)
started = time.perf_counter()
result = solver.solve(capture, options, lambda fraction, message: None)
seconds = time.perf_counter() - started
scored = score(np.where(result.mask[..., None], result.normal, np.float32(0.0)), capture.ground_truth)
with open("/proc/self/status") as status:
    peak_kb = next(int(line.split()[1]) for line in status if line.startswith("VmHWM:"))
d = result.diagnostics
print(json.dumps({"seconds": seconds, "mae_deg": scored.stats["mae_deg"], "coverage": scored.stats["coverage"],
                  "peak_gb": peak_kb * 1024 / 1e9, "pixels": int(result.mask.sum()), "event_pairs": d.get("event_pairs"),
                  "stages": d.get("seconds", {}), "preprocess_split": d.get("preprocess", {}).get("seconds", {}),
                  "torch_threads": torch.get_num_threads()}))
"""


def capture_path(folder: Path, size: int, seed: int) -> Path:
    """The blobs capture of ``size``² frame pixels in ``folder``, simulated the first time."""
    path = folder / f"blobs-{size}-seed{seed}.h5"
    if not path.exists():
        from pstoolkit.sim.simulator import SimulationConfig, simulate

        simulate(SimulationConfig(scene="blobs", size=size, seed=seed), path)
    return path


def solve_in_child(path: Path, threads: int, assignments: list[str]) -> dict[str, Any]:
    """The child's JSON line for one capture (its last line of output); RuntimeError when it fails."""
    done = subprocess.run([sys.executable, "-c", CHILD, str(path), str(threads), *assignments],
                          capture_output=True, text=True, env=os.environ.copy(), check=False)
    if done.returncode != 0:
        raise RuntimeError(f"dualres on {path} failed ({done.returncode}):\n{done.stderr[-4000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def row_of(size: int, child: dict[str, Any]) -> dict[str, Any]:
    frame_pixels = size * size
    return {"size": size, "event_size": size // 2, **child, "us_per_pixel": child["seconds"] / frame_pixels * 1e6}


def table(rows: list[dict[str, Any]]) -> None:
    """Print one line per size, then the stage split."""
    print(f"\n{'frames':>8} {'events':>8} {'solve s':>9} {'µs/px':>7} {'peak GB':>8} {'MAE°':>6}")
    for r in rows:
        print(f"{r['size']:>7}² {r['event_size']:>7}² {r['seconds']:9.1f} {r['us_per_pixel']:7.1f} {r['peak_gb']:8.2f} {r['mae_deg']:6.2f}")
    stages = list(dict.fromkeys(k for r in rows for k in r["stages"] if k != "total"))
    print(f"\nstage seconds{'':>7}" + "".join(f"{r['size']:>9}²" for r in rows))
    for stage in stages:
        print(f"{stage:<20}" + "".join(f"{r['stages'].get(stage, float('nan')):10.2f}" for r in rows))


def verdict(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The issue's acceptance criteria, each True/False (None when its size was not run)."""
    by = {r["size"]: r for r in rows}
    large, small = by.get(LARGE), by.get(SMALL)
    ratio = large["us_per_pixel"] / small["us_per_pixel"] if large and small else None
    return {
        "per_pixel_ratio_1024_to_256": ratio,
        "per_pixel_within_1.3x": None if ratio is None else ratio <= PER_PIXEL_RATIO,
        "seconds_1024": large["seconds"] if large else None,
        "within_120s_at_1024": None if not large else large["seconds"] <= TIME_LIMIT_S,
        "peak_gb_1024": large["peak_gb"] if large else None,
        "within_3gb_at_1024": None if not large else large["peak_gb"] <= MEMORY_LIMIT_GB,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="*", default=list(SIZES), help="frame sizes in pixels (default 256 512 1024)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=0, help="torch CPU threads of the solve (default: torch's choice)")
    parser.add_argument("--dualres-options", nargs="*", default=[], help="extra --set assignments (default: the default preset)")
    parser.add_argument("--data", type=Path, help="folder to keep the captures in (default: a temporary one)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.data or Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        for size in args.sizes:
            row = row_of(size, solve_in_child(capture_path(folder, size, args.seed), args.threads, args.dualres_options))
            rows.append(row)
            print(f"  {size}²: {row['seconds']:.1f} s, {row['us_per_pixel']:.1f} µs/px, {row['peak_gb']:.2f} GB, "
                  f"MAE {row['mae_deg']:.2f}°", flush=True)
    table(rows)
    checks = verdict(rows)
    print("\nacceptance:", json.dumps(checks, indent=1))
    write_results(args.out, {
        "benchmark": "dualres_scale",
        "config": {"scene": "blobs", "sizes": args.sizes, "seed": args.seed, "dualres_options": args.dualres_options,
                   "event_scale": 0.5},
        "machine": {"python": platform.python_version(), "processor": platform.processor() or platform.machine(),
                    "cpus": os.cpu_count(), "torch_threads": rows[0]["torch_threads"] if rows else None},
        "rows": rows, "acceptance": checks,
    })
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
