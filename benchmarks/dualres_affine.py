"""The ``dualres`` solver on captures whose event grid does not line up with the frame's.

A calibrated rig's event→frame affine has offsets that are no multiple of an event pixel, and its
event sensor often sees past the frame. Both are emulated on the simulator's ``blobs`` scene at
``--size`` (events at half resolution per axis, kept in ``--data``):

- ``crop``: the frames cropped to (N − 4)² starting ``offset`` px into the frame on both axes, with
  the events of the pixels that see the crop and the affine moved along (``crop_capture``, as tiles
  are cut): an odd offset is half an event pixel, and the outermost event pixels see past the crop;
- ``wider``: the same frame crop with every event of the sensor kept, so a band of event pixels
  sees nothing of the frames and the next one part of it.

Per row: MAE, median, coverage (share of ground-truth pixels solved), event pairs used, seconds.
Prints the table and writes ``benchmarks/results/dualres_affine.json`` (``--out``).

    python benchmarks/dualres_affine.py                       # 128 px, offsets 0 1 2 3
    python benchmarks/dualres_affine.py --size 256 --offsets 1 2 --data /tmp/blobs
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
from pstoolkit.evaluation.scoring import score
from pstoolkit.plugin.manager import get_registries
from pstoolkit.sim.config import SimulationConfig
from pstoolkit.sim.simulator import simulate
from pstoolkit.solve.base import run_solver
from pstoolkit.solve.tiles import Tile, crop_capture

RESULTS = Path(__file__).resolve().parent / "results" / "dualres_affine.json"
MARGIN_PX = 4


def wider(capture: psfmt.Capture, crop: psfmt.Capture, tile: Tile) -> psfmt.Capture:
    """``crop`` with every event of ``capture`` and the full affine moved by the crop's origin."""
    full = capture.calibration.event_to_frame
    affine = full.copy()
    affine[:, 2] -= np.array([tile.crop_left, tile.crop_top], dtype=np.float64)
    events = psfmt.Events(capture.events.width, capture.events.height, capture.events.read())
    return replace(crop, events=events, calibration=replace(crop.calibration, event_to_frame=affine))


def row(entry: Any, options: Any, capture: psfmt.Capture, case: str, offset: int) -> dict[str, Any]:
    start = time.perf_counter()
    result, _ = run_solver(entry, capture, options)
    seconds = time.perf_counter() - start
    stats = score(result.normal, capture.ground_truth).stats
    return {
        "case": case, "offset_px": offset, "affine_offset_px": capture.calibration.event_to_frame[:, 2].tolist(),
        "mae_deg": stats["mae_deg"], "median_deg": stats["median_deg"], "coverage": stats["coverage"],
        "event_pairs": result.diagnostics.get("event_pairs"), "seconds": seconds,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--offsets", type=int, nargs="*", default=[0, 1, 2, 3])
    parser.add_argument("--dualres-options", nargs="*", default=[], help="extra --set assignments of dualres")
    parser.add_argument("--data", type=Path, default=None, help="folder keeping the simulated capture")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    data = args.data or Path("benchmarks/results/data")
    data.mkdir(parents=True, exist_ok=True)
    path = data / f"blobs-{args.size}-seed{args.seed}.h5"
    if not path.exists():
        simulate(SimulationConfig(scene="blobs", size=args.size, seed=args.seed), path)
    entry = get_registries().solvers.get("dualres")
    options = entry.parse_options(["tile_px=-1", *args.dualres_options])
    rows = []
    n = args.size - MARGIN_PX
    print(f"{'case':<6} {'offset':>6} {'affine offset':>15} {'MAE °':>7} {'median °':>9} {'coverage':>9} {'pairs':>8} {'s':>6}")
    with psfmt.read(path) as capture:
        for offset in args.offsets:
            tile = Tile(0, 1, 1, 0, n, 0, n, offset, offset + n, offset, offset + n)
            crop = crop_capture(capture, tile)
            for case, source in (("crop", crop), ("wider", wider(capture, crop, tile))):
                r = row(entry, options, source, case, offset)
                rows.append(r)
                print(f"{case:<6} {offset:>6} {str([round(x, 2) for x in r['affine_offset_px']]):>15} {r['mae_deg']:7.3f} "
                      f"{r['median_deg']:9.3f} {100 * r['coverage']:8.1f}% {r['event_pairs']:>8} {r['seconds']:6.1f}", flush=True)
    write_results(args.out, {
        "machine": {"python": platform.python_version(), "processor": platform.processor() or platform.machine()},
        "config": {"size": args.size, "seed": args.seed, "crop_px": n, "dualres_options": args.dualres_options},
        "rows": rows,
    })
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
