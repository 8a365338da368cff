"""``eventps`` under sensor non-idealities against ``frameps`` with 24 lights.

For each scene (default ``blobs`` and ``relief``, GGX materials, cast shadows) a classic capture of 24
instantaneous lights (ideal 8-bit frames) and hybrid captures at ``--size`` (events at half that,
C = 0.15, R = 2 ms, one turn) for each sensor:

- ``ideal``: "reset-at-end", equal thresholds everywhere;
- ``rate-limited``: ``--refractory-rule rate-limited``;
- ``spread``: per-pixel, per-polarity thresholds ``--contrast-sigma 0.03``;
- ``noise``: ``ideal`` plus ``--background-hz`` of uniform background events per pixel, ``--hot``
  hot pixels at ``--hot-hz`` and a calibration whose C⁺/C⁻ are off by ±10 % (added after simulation,
  ``tests/helpers/event_noise.py``);
- ``all``: rate-limited, spread and noise together.

Rows: MAE, median and 90th percentile (°) over the ground-truth mask as ``pstoolkit run`` scores them,
and solver seconds. Acceptance (printed, stored): eventps within 2× of frameps 24 on every capture.
Prints the table and writes ``benchmarks/results/eventps_sensors.json``.

    python benchmarks/eventps_sensors.py                 # 128 px frames, 64 px events
    python benchmarks/eventps_sensors.py --scenes blobs --size 64
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from results_io import write_results

import psfmt
from pstoolkit.evaluation.metrics import angular_error_deg
from pstoolkit.plugin.manager import get_registries
from pstoolkit.sim.config import SimulationConfig
from pstoolkit.sim.simulator import simulate
from pstoolkit.solve.base import run_solver

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from helpers.event_noise import with_noise  # noqa: E402

SENSORS: dict[str, dict[str, Any]] = {
    "ideal": {},
    "rate-limited": {"refractory_rule": "rate-limited"},
    "spread": {"contrast_sigma": 0.03},
    "noise": {},
    "all": {"refractory_rule": "rate-limited", "contrast_sigma": 0.03},
}
NOISY = ("noise", "all")


def row(solver: str, capture: psfmt.Capture) -> dict[str, Any]:
    """MAE, median, 90th percentile (°, over the mask, unsolved pixels as 90°) and seconds of one run."""
    entry = get_registries().solvers.get(solver)
    result, seconds = run_solver(entry, capture, entry.parse_options([]))
    gt = capture.ground_truth
    normal = np.where(result.mask[..., None], result.normal, np.float32(0.0))
    errors = angular_error_deg(normal, gt.normal, gt.mask)[gt.mask]
    errors = np.where(np.isfinite(errors), errors, 90.0)
    return {"mae_deg": float(errors.mean()), "median_deg": float(np.median(errors)),
            "p90_deg": float(np.percentile(errors, 90)), "seconds": seconds}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=["blobs", "relief"])
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--background-hz", type=float, default=10.0)
    parser.add_argument("--hot", type=int, default=4)
    parser.add_argument("--hot-hz", type=float, default=3000.0)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "eventps_sensors.json")
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for scene in args.scenes:
            common = {"scene": scene, "size": args.size, "seed": args.seed}
            classic = Path(tmp) / f"{scene}-24.h5"
            simulate(SimulationConfig(discrete_lights=24, **common), classic)
            frameps = row("frameps", psfmt.load(classic))
            for sensor, options in SENSORS.items():
                path = Path(tmp) / f"{scene}-{sensor}.h5"
                simulate(SimulationConfig(**common, **options), path)
                capture = psfmt.load(path)
                if sensor in NOISY:
                    cal = capture.calibration
                    capture = with_noise(capture, background_hz=args.background_hz, hot_pixels=args.hot, hot_hz=args.hot_hz,
                                         contrast_pos=1.1 * cal.contrast_pos, contrast_neg=0.9 * cal.contrast_neg, seed=args.seed)
                eventps = row("eventps", capture)
                rows.append({"scene": scene, "sensor": sensor, "eventps": eventps, "frameps_24": frameps,
                             "within_2x": eventps["mae_deg"] <= 2.0 * frameps["mae_deg"]})
                print(f"{scene:8} {sensor:13} eventps {eventps['mae_deg']:6.2f} {eventps['median_deg']:6.2f} "
                      f"{eventps['p90_deg']:6.2f} {eventps['seconds']:6.2f} s | frameps 24 {frameps['mae_deg']:6.2f} "
                      f"{frameps['median_deg']:6.2f} {frameps['p90_deg']:6.2f} {frameps['seconds']:6.2f} s", flush=True)
    verdict = {"within_2x_every_capture": all(r["within_2x"] for r in rows)}
    print(f"eventps within 2x of frameps 24 on every capture: {verdict['within_2x_every_capture']}")
    write_results(args.out, {"size": args.size, "seed": args.seed, "background_hz": args.background_hz, "hot_pixels": args.hot,
                             "hot_hz": args.hot_hz, "rows": rows, "verdict": verdict})


if __name__ == "__main__":
    main()
