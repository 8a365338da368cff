"""A simulated DAVIS recording through AEDAT4 and back, then dualres on both (extra ``aedat4``).

Simulates the blobs scene with frames and events on one grid (``--event-scale 1``, as a DAVIS346's
pixels), writes its events, RGB frames (with their exposure windows) and the trigger edges of each
exposure as an AEDAT4 file with dv-processing's ``MonoCameraWriter``, converts that file back with
``pstoolkit convert aedat4 --lights SIM --calibration SIM``, checks that events, frames and windows
came back identical, and runs ``dualres`` (same seed and options) on the simulated capture and on the
converted one. Both MAEs are against the simulation's ground truth; identical inputs should give the
same MAE. Prints a table and writes ``benchmarks/results/aedat4_roundtrip.json``.

    python benchmarks/aedat4_roundtrip.py [--size 32] [--epochs 3] [--seed 0]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import dv_processing as dv
import numpy as np
from results_io import write_results

import psfmt
from pstoolkit.cli import main as cli
from pstoolkit.evaluation.metrics import angular_error_deg

RESULTS = Path(__file__).resolve().parent / "results" / "aedat4_roundtrip.json"


def write_aedat4(capture: psfmt.Capture, path: Path) -> None:
    """The capture's events, frames and exposure trigger edges as one DAVIS-like AEDAT4 file."""
    events, frames = capture.events, capture.frames
    config = dv.io.MonoCameraWriter.Config("DAVIS346_sim")
    config.addEventStream((events.width, events.height))
    config.addFrameStream((frames.width, frames.height))
    config.addTriggerStream()
    writer = dv.io.MonoCameraWriter(str(path), config)
    for block in events.chunks():
        store = dv.EventStore()
        for t, x, y, p in zip(block.t.tolist(), block.x.tolist(), block.y.tolist(), block.p.tolist()):
            store.push_back(t, x, y, p > 0)
        writer.writeEvents(store)
    data = np.asarray(frames.data)
    for k in range(frames.count):
        start, end = int(frames.t_start_us[k]), int(frames.t_end_us[k])
        writer.writeFrame(dv.Frame(start, end - start, 0, 0, np.ascontiguousarray(data[k][..., ::-1]), dv.FrameSource.SENSOR))
    for k in range(frames.count):
        writer.writeTrigger(dv.Trigger(int(frames.t_start_us[k]), dv.TriggerType.EXTERNAL_SIGNAL_RISING_EDGE))
        writer.writeTrigger(dv.Trigger(int(frames.t_end_us[k]), dv.TriggerType.EXTERNAL_SIGNAL_FALLING_EDGE))
    del writer  # closing writes the file's table


def solve(capture: Path, out: Path, epochs: int, seed: int) -> tuple[np.ndarray, float]:
    started = time.perf_counter()
    code = cli(["run", str(capture), "--solver", "dualres", "-o", str(out), "-q", "--set", f"epochs={epochs}", "--set", f"seed={seed}"])
    if code != 0:
        raise SystemExit(f"dualres on {capture} exited with {code}")
    return np.load(out / "normal.npy"), time.perf_counter() - started


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=32)
    parser.add_argument("--epochs", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        sim, rec, conv = folder / "sim.h5", folder / "rec.aedat4", folder / "conv.h5"
        cli(["simulate", "blobs", "-o", str(sim), "--size", str(args.size), "--seed", str(args.seed), "--event-scale", "1", "-q"])
        with psfmt.read(sim) as capture:
            write_aedat4(capture, rec)
        started = time.perf_counter()
        assert cli(["convert", "aedat4", str(rec), "-o", str(conv), "--lights", str(sim), "--calibration", str(sim), "-q"]) == 0
        convert_s = time.perf_counter() - started
        with psfmt.read(sim) as a, psfmt.read(conv) as b:
            ea, eb = a.events.read(), b.events.read()
            identical = {
                "events": all(np.array_equal(getattr(ea, c), getattr(eb, c)) for c in "xytp"),
                "frames": bool(np.array_equal(np.asarray(a.frames.data), np.asarray(b.frames.data))),
                "windows": bool(np.array_equal(a.frames.t_start_us, b.frames.t_start_us) and np.array_equal(a.frames.t_end_us, b.frames.t_end_us)),
                "affine": bool(np.array_equal(a.calibration.event_to_frame, b.calibration.event_to_frame)),
            }
            gt = a.ground_truth
            n_events = len(ea)
        rows = []
        for name, capture in (("simulated capture", sim), ("through AEDAT4", conv)):
            normal, seconds = solve(capture, folder / name.replace(" ", "_"), args.epochs, args.seed)
            mae = float(angular_error_deg(normal, gt.normal, gt.mask)[gt.mask].mean())
            rows.append({"capture": name, "mae_deg": mae, "seconds": seconds})
    print(f"blobs {args.size}×{args.size}, event scale 1, {n_events:,} events → AEDAT4 → capture (convert {convert_s:.2f} s)")
    print("identical after the round trip: " + ", ".join(f"{k} {'yes' if v else 'NO'}" for k, v in identical.items()))
    print(f"{'dualres on':20} {'MAE °':>8} {'seconds':>8}")
    for r in rows:
        print(f"{r['capture']:20} {r['mae_deg']:8.3f} {r['seconds']:8.1f}")
    write_results(RESULTS, {"size": args.size, "epochs": args.epochs, "seed": args.seed, "events": n_events,
                            "convert_seconds": convert_s, "identical": identical, "rows": rows})
    print(json.dumps({"mae_difference_deg": abs(rows[0]["mae_deg"] - rows[1]["mae_deg"])}))


if __name__ == "__main__":
    main()
