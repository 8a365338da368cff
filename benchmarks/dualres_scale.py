"""How the ``dualres`` solver's time and memory grow with the capture's resolution (issue 26).

For each ``--sizes`` N (or HxW): the simulator's ``blobs`` scene at N² frame pixels (events at half
that per axis, the defaults of ``pstoolkit simulate``; an H×W capture is the top-left crop of the
max(H, W)² scene, cut as the tiled solver cuts tiles), kept in ``--data`` between runs, solved by
``dualres`` with its default preset and ``--dualres-options`` in a child process. Peak memory is
that of the child and every process it starts (a tiled solve's local cluster: scheduler, nannies,
workers), their resident sizes summed and sampled every 0.2 s (``peak_gb``); ``driver_peak_gb`` is
the child's own VmHWM. Per size: solve seconds, microseconds per frame pixel, peak memory, MAE, the
tiling (tiles, largest crop), the MAE in the seams' blending bands and off them, and, untiled, the wall seconds of the solver's stages
(``diagnostics["seconds"]``: preprocess, detect, closed_form, problem, field, train_<stage>,
redetect_<stage>, output; preprocessing's own split under ``preprocess_split``).

Acceptance (printed, stored in the JSON; a criterion whose size was not run is None): time per pixel
at 1024² within 1.3× of 256²; 1024² solved in at most 120 s; peak memory at 1024² at most 3 GB.
Seconds are wall seconds on this machine with torch's threads (``--threads``, default: torch's
choice).

Prints the table and writes ``benchmarks/results/dualres_scale.json`` (``--out``).

    python benchmarks/dualres_scale.py                          # 256, 512, 1024
    python benchmarks/dualres_scale.py --sizes 256 512 --data /tmp/blobs
    python benchmarks/dualres_scale.py --sizes 512 1024 2048x2448 --dualres-options memory_gb=3 \
        --out benchmarks/results/dualres_scale-tiled.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import threading
from pathlib import Path
from typing import Any

import psutil
from results_io import write_results

import psfmt

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
from pstoolkit.evaluation.metrics import angular_error_deg
from pstoolkit.evaluation.scoring import score
from pstoolkit.plugin.manager import get_registries
from pstoolkit.solve.base import run_solver

path, threads, assignments = sys.argv[1], int(sys.argv[2]), sys.argv[3:]
if threads:
    torch.set_num_threads(threads)
capture = psfmt.read(path)
entry = get_registries().solvers.get("dualres")
options = entry.parse_options(assignments)
started = time.perf_counter()
result, _ = run_solver(entry, capture, options, device="cpu")
seconds = time.perf_counter() - started
scored = score(np.where(result.mask[..., None], result.normal, np.float32(0.0)), capture.ground_truth)
with open("/proc/self/status") as status:
    peak_kb = next(int(line.split()[1]) for line in status if line.startswith("VmHWM:"))
d = result.diagnostics
seam = None
if d.get("tiling"):
    # the error in the blending bands (overlap_px wide, centred on each core boundary) and off them
    truth = capture.ground_truth
    error = angular_error_deg(result.normal, truth.normal, truth.mask)
    tiling, half = d["tiling"], d["tiling"]["overlap_px"] / 2
    rows, cols = np.mgrid[0:error.shape[0], 0:error.shape[1]] + 0.5
    band = np.zeros(error.shape, dtype=bool)
    for cut in tiling["row_cuts"]:
        band |= np.abs(rows - cut) < half
    for cut in tiling["col_cuts"]:
        band |= np.abs(cols - cut) < half
    seam = {"band_mae_deg": float(error[truth.mask & band].mean()), "off_band_mae_deg": float(error[truth.mask & ~band].mean())}
print(json.dumps({"seconds": seconds, "mae_deg": scored.stats["mae_deg"], "coverage": scored.stats["coverage"],
                  "driver_peak_gb": peak_kb * 1024 / 1e9, "pixels": int(result.mask.sum()), "event_pairs": d.get("event_pairs"),
                  "stages": d.get("seconds", {}), "preprocess_split": d.get("preprocess", {}).get("seconds", {}),
                  "tiling": d.get("tiling"), "seam": seam, "torch_threads": torch.get_num_threads()}))
"""


def parse_size(text: str) -> tuple[int, int]:
    """``N`` → (N, N); ``HxW`` → (H, W)."""
    height, _, width = text.lower().partition("x")
    return int(height), int(width or height)


def size_name(shape: tuple[int, int]) -> str:
    return f"{shape[0]}²" if shape[0] == shape[1] else f"{shape[0]}×{shape[1]}"


def capture_path(folder: Path, shape: tuple[int, int], seed: int) -> Path:
    """The blobs capture of ``shape`` frame pixels in ``folder``, simulated (and cropped) the first time."""
    height, width = shape
    side = max(height, width)
    square = folder / f"blobs-{side}-seed{seed}.h5"
    if not square.exists():
        from pstoolkit.sim.config import SimulationConfig
        from pstoolkit.sim.simulator import simulate

        simulate(SimulationConfig(scene="blobs", size=side, seed=seed), square)
    if height == width:
        return square
    path = folder / f"blobs-{height}x{width}-seed{seed}.h5"
    if not path.exists():
        from pstoolkit.solve.tiles import Tile, crop_capture

        whole = Tile(0, 1, 1, 0, height, 0, width, 0, height, 0, width)
        with psfmt.read(square) as capture:
            psfmt.write(crop_capture(capture, whole), path)
    return path


def _tree_rss(process: psutil.Process) -> int:
    """Resident bytes of ``process`` and all its descendants (those that vanish meanwhile count 0)."""
    total = 0
    for p in [process, *process.children(recursive=True)]:
        try:
            total += p.memory_info().rss
        except psutil.Error:
            pass
    return total


def solve_in_child(path: Path, threads: int, assignments: list[str]) -> dict[str, Any]:
    """The child's JSON line for one capture (its last line of output) with ``peak_gb``, the peak of
    its process tree's summed resident memory; RuntimeError when it fails."""
    child = subprocess.Popen([sys.executable, "-c", CHILD, str(path), str(threads), *assignments],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=os.environ.copy())
    peak = 0
    watched = psutil.Process(child.pid)
    done = threading.Event()

    def sample() -> None:
        nonlocal peak
        while not done.wait(0.2):
            peak = max(peak, _tree_rss(watched))

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    out, err = child.communicate()
    done.set()
    sampler.join()
    if child.returncode != 0:
        raise RuntimeError(f"dualres on {path} failed ({child.returncode}):\n{err[-4000:]}")
    return {**json.loads(out.strip().splitlines()[-1]), "peak_gb": max(peak, 0) / 1e9}


def row_of(shape: tuple[int, int], child: dict[str, Any]) -> dict[str, Any]:
    height, width = shape
    frame_pixels = height * width
    return {"size": size_name(shape), "height": height, "width": width, "event_size": size_name((height // 2, width // 2)),
            **child, "us_per_pixel": child["seconds"] / frame_pixels * 1e6}


def table(rows: list[dict[str, Any]]) -> None:
    """Print one line per size, then the stage split of the untiled ones."""
    print(f"\n{'frames':>10} {'events':>10} {'tiles':>5} {'solve s':>9} {'µs/px':>7} {'peak GB':>8} {'MAE°':>6} {'seams°':>7}")
    for r in rows:
        tiles = r["tiling"]["tiles"] if r.get("tiling") else 1
        seam = f"{r['seam']['band_mae_deg']:.2f}/{r['seam']['off_band_mae_deg']:.2f}" if r.get("seam") else "-"
        print(f"{r['size']:>10} {r['event_size']:>10} {tiles:>5} {r['seconds']:9.1f} {r['us_per_pixel']:7.1f} {r['peak_gb']:8.2f} "
              f"{r['mae_deg']:6.2f} {seam:>9}")
    whole = [r for r in rows if r["stages"]]
    if not whole:
        return
    stages = list(dict.fromkeys(k for r in whole for k in r["stages"] if k != "total"))
    print(f"\nstage seconds{'':>7}" + "".join(f"{r['size']:>10}" for r in whole))
    for stage in stages:
        print(f"{stage:<20}" + "".join(f"{r['stages'].get(stage, float('nan')):10.2f}" for r in whole))


def verdict(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The issue's acceptance criteria, each True/False (None when its size was not run)."""
    by = {r["size"]: r for r in rows}
    large, small = by.get(size_name((LARGE, LARGE))), by.get(size_name((SMALL, SMALL)))
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
    parser.add_argument("--sizes", nargs="*", default=[str(n) for n in SIZES],
                        help="frame sizes in pixels, N or HxW (default 256 512 1024)")
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
        for text in args.sizes:
            shape = parse_size(text)
            row = row_of(shape, solve_in_child(capture_path(folder, shape, args.seed), args.threads, args.dualres_options))
            rows.append(row)
            print(f"  {row['size']}: {row['seconds']:.1f} s, {row['us_per_pixel']:.1f} µs/px, {row['peak_gb']:.2f} GB, "
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
