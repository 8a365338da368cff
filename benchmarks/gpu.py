"""DualResPS on a CUDA GPU against the CPU of the same machine (issue 36), in one command.

Sections, each a table printed and stored in the JSON:

1. ``fast`` (the default preset) on the simulator's ``blobs`` scene at ``--sizes`` frame pixels (events
   at half that per axis; an H×W capture is the top-left crop of the max(H, W)² scene, as
   ``dualres_scale.py`` cuts it), ``--device cuda`` at every size and ``--device cpu`` at
   ``--cpu-sizes``: wall seconds of the solve, MAE, median and 90th percentile against the ground truth,
   the GPU's peak allocated memory, and the wall seconds of the solver's stages
   (``diagnostics["seconds"]``, preprocessing's own split beside them). Every solve follows a warm-up
   solve of a 64² capture on the same device in this process, so numba's kernels are compiled and
   CUDA's context and libraries loaded before any timed run ("second run").
2. ``paper`` (the paper's MLP) at each of ``--paper-sizes`` on cuda, its mini-batch steps replayed as
   CUDA graphs, with the solver's ``compile`` off and on (``--paper-compile``) and any more options
   (``--paper-options``, such as ``batch_pixels=4096``): ``--paper-epochs``
   epochs, or as many as a first timed run of ``PROBE_EPOCHS`` says fit in ``--paper-budget-s``
   (that first run also compiles, so the timed run's compiled steps come from torch's caches);
   the training stages' seconds per epoch (``train_*`` of the stage table, over the epochs asked for,
   which ``interreflection=auto`` trains partly twice), the 1200 epochs they project to beside the
   solve's other stages, and the errors.
3. With ``--tests``: the suite's CUDA tests (``pytest -m cuda``), their summary line; run first, since
   they check what the timings rest on (and a run cut short at its limit keeps them).

``--profile SIZE …`` also runs cProfile over the cuda solve of that size (``paper``: the paper preset's
runs) and writes the functions that take the most time (cumulative and own) to ``profile-SIZE.txt``
beside the JSON. ``--kernels SIZE …`` solves that size once more under torch's profiler: the operators
and CUDA kernels that take the most time go to ``kernels-SIZE.txt``, and the row keeps the seconds the
GPU was busy (its kernels' time) beside the solve's: a GPU busy for a small share of the solve waits on
the host.

A solve that fails is a row with its ``error`` (printed, and kept in the JSON), and the runs after it go
on: one fault costs its row, not the device session.

Targets (issue 36, one H100, printed with the table): fast 256² ≤ 2 s, 1024² ≤ 8 s, 2048×2448 ≤ 40 s,
each MAE within 0.02° of the CPU's; paper 1200 epochs at 256² ≤ 60 s. Seconds are wall seconds, the
device synchronised before the clock is read.

    python benchmarks/gpu.py                                   # everything, about 5 minutes on an H100
    python benchmarks/gpu.py --sizes 256 1024 --cpu-sizes 256 --profile 1024 --out /tmp/gpu.json
"""

from __future__ import annotations

import argparse
import contextlib
import cProfile
import io
import json
import os
import platform
import pstats
import subprocess
import sys
import tempfile
import time
import traceback
from pathlib import Path
from typing import Any

import numpy as np
import torch
from dualres_scale import capture_path, parse_size, size_name
from results_io import write_results
from torch.autograd import DeviceType
from torch.profiler import ProfilerActivity

import psfmt
from pstoolkit.evaluation.metrics import angular_error_deg
from pstoolkit.plugin.manager import get_registries
from pstoolkit.solve.base import run_solver

RESULTS = Path(__file__).resolve().parent / "results" / "gpu.json"
SIZES = ("256", "1024", "2048x2448")
CPU_SIZES = ("256", "1024")
WARM_UP = 64
PROBE_EPOCHS = 12
TARGET_S = {"256²": 2.0, "1024²": 8.0, "2048×2448": 40.0}
PAPER_TARGET_S = 60.0
PAPER_EPOCHS = 1200
PAPER_SIZE = "256²"
MAE_TOLERANCE_DEG = 0.02


def synchronize(device: str) -> None:
    if device == "cuda":
        torch.cuda.synchronize()


def solve(path: Path, device: str, assignments: list[str], profile: Path | None = None, kernels: Path | None = None
          ) -> dict[str, Any]:
    """One dualres solve of the capture at ``path`` on ``device``: seconds, errors, stages, GPU memory;
    under cProfile with ``profile`` (its tables written there), or torch's profiler with ``kernels``
    (``write_kernels``; the row's ``device_busy_s`` and ``kernel_launches``)."""
    entry = get_registries().solvers.get("dualres")
    options = entry.parse_options(assignments)
    activities = [ProfilerActivity.CPU, *([ProfilerActivity.CUDA] if device == "cuda" else [])]
    with psfmt.read(path) as capture:
        truth = capture.ground_truth
        if device == "cuda":
            torch.cuda.reset_peak_memory_stats()
        profiler = cProfile.Profile() if profile else None
        synchronize(device)
        started = time.perf_counter()
        if profiler:
            profiler.enable()
        with torch.profiler.profile(activities=activities) if kernels else contextlib.nullcontext() as traced:
            result, _ = run_solver(entry, capture, options, device=device)
            synchronize(device)
        seconds = time.perf_counter() - started
        if profiler:
            profiler.disable()
            write_profile(profiler, profile)
    error = angular_error_deg(result.normal, truth.normal, truth.mask)[truth.mask & result.mask]
    d = result.diagnostics
    return {
        "device": device, "seconds": seconds, "mae_deg": float(np.mean(error)), "median_deg": float(np.median(error)),
        "p90_deg": float(np.percentile(error, 90)), "coverage": float((truth.mask & result.mask).sum() / truth.mask.sum()),
        "gpu_peak_gb": torch.cuda.max_memory_allocated() / 1e9 if device == "cuda" else None,
        "stages": d.get("seconds", {}), "preprocess_split": d.get("preprocess", {}).get("seconds", {}),
        "tiling": d.get("tiling"), "epochs": d.get("preset", {}).get("epochs"),
        **(write_kernels(traced, kernels, device) if kernels else {}),
    }


def write_kernels(traced: torch.profiler.profile, path: Path, device: str) -> dict[str, Any]:
    """The operators (and on CUDA the kernels) that took the most time in a solve under torch's profiler,
    written to ``path``; the seconds the device was busy (its kernels' time: a device busy for a small
    share of the solve waits on the host) and its kernel launches."""
    averages = traced.key_averages()
    kernels = [event for event in averages if event.device_type == DeviceType.CUDA]
    order = "self_device_time_total" if device == "cuda" else "self_cpu_time_total"
    path.write_text(averages.table(sort_by=order, row_limit=60) + "\n" + averages.table(sort_by="cpu_time_total", row_limit=40))
    return {"device_busy_s": sum(event.self_device_time_total for event in kernels) / 1e6 if device == "cuda" else None,
            "kernel_launches": sum(event.count for event in kernels)}


def write_profile(profiler: cProfile.Profile, path: Path) -> None:
    text = io.StringIO()
    stats = pstats.Stats(profiler, stream=text)
    stats.sort_stats("cumulative").print_stats(60)
    stats.sort_stats("tottime").print_stats(40)
    path.write_text(text.getvalue())


def failed(what: str, error: Exception) -> dict[str, Any]:
    """The record of a run that raised: its error, printed (the runs after it go on)."""
    text = f"{type(error).__name__}: {error}"
    print(f"  {what}: FAILED {text}", flush=True)
    traceback.print_exc()
    return {"error": text}


def fast_rows(folder: Path, gpu: str, sizes: list[str], cpu_sizes: list[str], options: list[str], profile: list[str],
              kernels: list[str], out: Path) -> list[dict[str, Any]]:
    rows = []
    for text in sizes:
        shape = parse_size(text)
        for device in (gpu, "cpu") if text in cpu_sizes else (gpu,):
            where = out.parent / f"profile-{text}.txt" if device == gpu and text in profile else None
            row: dict[str, Any] = {"size": size_name(shape), "device": device}
            try:
                row.update(solve(capture_path(folder, shape, 0), device, options, where))
            except Exception as error:  # noqa: BLE001 -- one failed row must not end the device session
                row.update(failed(f"fast {row['size']} {device}", error))
            else:
                print(f"  fast {row['size']} {device}: {row['seconds']:.2f} s, MAE {row['mae_deg']:.3f}° "
                      f"(median {row['median_deg']:.3f}°, p90 {row['p90_deg']:.3f}°); stages {row['stages']}; "
                      f"preprocess {row['preprocess_split']}", flush=True)
                if device == gpu and text in kernels:
                    row["kernels"] = kernel_row(capture_path(folder, shape, 0), device, options, out.parent / f"kernels-{text}.txt")
            rows.append(row)
    return rows


def kernel_row(path: Path, device: str, options: list[str], where: Path) -> dict[str, Any]:
    """The same solve again under torch's profiler (``solve``'s ``kernels``): the seconds its device was
    busy, its kernel launches, the solve's seconds under the profiler (slower than the row's)."""
    try:
        traced = solve(path, device, options, kernels=where)
    except Exception as error:  # noqa: BLE001 -- the profile is extra: its failure leaves the row
        return failed(f"kernels {path.name} {device}", error)
    busy = traced["device_busy_s"]
    print(f"  kernels {path.stem} {device}: {traced['kernel_launches']} kernels"
          + (f", the device busy {busy:.2f} s" if busy is not None else "")
          + f" of a {traced['seconds']:.2f} s solve under the profiler; tables in {where}", flush=True)
    return {name: traced[name] for name in ("seconds", "device_busy_s", "kernel_launches")}


def training_seconds(row: dict[str, Any]) -> float:
    """The seconds of a solve's training stages (``train_*`` of its stage table)."""
    return sum(seconds for stage, seconds in row["stages"].items() if stage.startswith("train"))


def paper_row(folder: Path, gpu: str, size: str, epochs: int, budget_s: float, compiled: bool, extra: list[str],
              profile: Path | None) -> dict[str, Any]:
    """The paper preset on ``gpu`` (``compiled``: the solver's ``compile``; ``extra``: more assignments,
    such as another ``batch_pixels``): a probe of PROBE_EPOCHS epochs, then ``epochs`` or as many as fit
    the budget. An epoch's seconds are the training stages' over the epochs asked for; the projection of
    PAPER_EPOCHS adds the solve's other stages once."""
    name = size_name(parse_size(size))
    record: dict[str, Any] = {"size": name, "device": gpu, "compile": compiled, "options": extra}
    options = ["preset=paper", f"compile={'true' if compiled else 'false'}", *extra]
    try:
        path = capture_path(folder, parse_size(size), 0)
        probe = solve(path, gpu, [*options, f"epochs={PROBE_EPOCHS}"])
        probe_per_epoch = training_seconds(probe) / PROBE_EPOCHS
        fixed = probe["seconds"] - training_seconds(probe)
        run = min(epochs, max(PROBE_EPOCHS, int((budget_s - fixed) / max(probe_per_epoch, 1e-9))))
        row = solve(path, gpu, [*options, f"epochs={run}"], profile)
    except Exception as error:  # noqa: BLE001 -- one failed row must not end the device session
        return {**record, **failed(f"paper {name} {gpu} compile={compiled}", error)}
    trained = training_seconds(row)
    per_epoch = trained / run
    print(f"  paper {name} {gpu} compile={compiled}: {run} epochs in {row['seconds']:.1f} s, training {trained:.1f} s "
          f"({per_epoch * 1e3:.1f} ms/epoch; probe {probe['seconds']:.1f} s), MAE {row['mae_deg']:.3f}°", flush=True)
    return {**record, "probe_seconds": probe["seconds"], "probe_seconds_per_epoch": probe_per_epoch, "epochs_run": run,
            "seconds_per_epoch": per_epoch, "projected_seconds": row["seconds"] - trained + per_epoch * PAPER_EPOCHS, **row}


def cuda_tests() -> dict[str, Any]:
    root = Path(__file__).resolve().parent.parent
    done = subprocess.run([sys.executable, "-m", "pytest", "-m", "cuda", "-p", "no:cacheprovider", "-q", "-rs",
                           "--continue-on-collection-errors"], cwd=root,
                          capture_output=True, text=True)
    lines = done.stdout.strip().splitlines()
    print("\n".join(lines[-15:]))
    return {"returncode": done.returncode, "summary": lines[-1] if lines else ""}


def table(rows: list[dict[str, Any]]) -> None:
    print(f"\n{'fast':>10} {'device':>6} {'seconds':>8} {'target':>7} {'MAE°':>7} {'median°':>8} {'p90°':>6} {'GPU GB':>7}")
    for r in (r for r in rows if "error" in r):
        print(f"{r['size']:>10} {r['device']:>6}   failed: {r['error'][:160]}")
    rows = [r for r in rows if "error" not in r]
    for r in rows:
        target = TARGET_S.get(r["size"]) if r["device"] == "cuda" else None
        gpu = f"{r['gpu_peak_gb']:.2f}" if r["gpu_peak_gb"] is not None else "-"
        print(f"{r['size']:>10} {r['device']:>6} {r['seconds']:8.2f} {target if target else '-':>7} {r['mae_deg']:7.3f} "
              f"{r['median_deg']:8.3f} {r['p90_deg']:6.3f} {gpu:>7}")
    stages = list(dict.fromkeys(k for r in rows for k in r["stages"] if k != "total"))
    split = list(dict.fromkeys(k for r in rows for k in r["preprocess_split"] if k != "total"))
    print(f"\n{'stage seconds':<20}" + "".join(f"{r['size'] + ' ' + r['device']:>16}" for r in rows))
    for stage in stages:
        print(f"{stage:<20}" + "".join(f"{r['stages'].get(stage, float('nan')):16.2f}" for r in rows))
    for stage in split:
        print(f"{'  pre.' + stage:<20}" + "".join(f"{r['preprocess_split'].get(stage, float('nan')):16.2f}" for r in rows))


def verdict(rows: list[dict[str, Any]], papers: list[dict[str, Any]]) -> dict[str, Any]:
    """The issue's targets, each True/False (None where its run is missing)."""
    checks: dict[str, Any] = {}
    rows, papers = [r for r in rows if "error" not in r], [p for p in papers if "error" not in p]
    for size, limit in TARGET_S.items():
        gpu = next((r for r in rows if r["size"] == size and r["device"] == "cuda"), None)
        cpu = next((r for r in rows if r["size"] == size and r["device"] == "cpu"), None)
        checks[f"fast_{size}_within_{limit:g}s"] = None if gpu is None else gpu["seconds"] <= limit
        checks[f"fast_{size}_mae_gap_deg"] = None if gpu is None or cpu is None else gpu["mae_deg"] - cpu["mae_deg"]
        checks[f"fast_{size}_mae_within_{MAE_TOLERANCE_DEG}"] = (None if gpu is None or cpu is None
                                                                 else abs(gpu["mae_deg"] - cpu["mae_deg"]) <= MAE_TOLERANCE_DEG)
    paper = min((p for p in papers if p["size"] == PAPER_SIZE and p["device"] == "cuda"), key=lambda p: p["projected_seconds"],
                default=None)
    checks[f"paper_{PAPER_EPOCHS}_epochs_at_{PAPER_SIZE}_within_{PAPER_TARGET_S:g}s"] = (None if paper is None
                                                                         else paper["projected_seconds"] <= PAPER_TARGET_S)
    return checks


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", nargs="*", default=list(SIZES), help="fast preset on cuda at these sizes, N or HxW")
    parser.add_argument("--cpu-sizes", nargs="*", default=list(CPU_SIZES), help="and on cpu at these (among --sizes)")
    parser.add_argument("--dualres-options", nargs="*", default=[], help="extra --set assignments of the fast runs")
    parser.add_argument("--paper-sizes", nargs="*", default=["256"], help="captures of the paper preset's runs (none: skipped)")
    parser.add_argument("--paper-epochs", type=int, default=PAPER_EPOCHS)
    parser.add_argument("--paper-budget-s", type=float, default=60.0, help="at most this long a paper run (fewer epochs)")
    parser.add_argument("--paper-compile", choices=("off", "on", "both"), default="both",
                        help="the paper runs with the solver's compile off, on, or both")
    parser.add_argument("--paper-options", nargs="*", default=[],
                        help="extra --set assignments of the paper runs (batch_pixels=4096: fewer, larger steps an epoch)")
    parser.add_argument("--profile", nargs="*", default=[], help="sizes of --sizes whose cuda solve runs under cProfile, and/or 'paper'")
    parser.add_argument("--kernels", nargs="*", default=[],
                        help="sizes of --sizes whose cuda solve runs again under torch's profiler: the operators and kernels that "
                             "take the most time (kernels-SIZE.txt beside the JSON), the seconds the GPU was busy")
    parser.add_argument("--tests", action="store_true", help="first run the suite's CUDA tests (pytest -m cuda)")
    parser.add_argument("--data", type=Path, help="folder to keep the captures in (default: a temporary one)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--device", default="cuda", help="the device under test (cpu only tries this script out)")
    args = parser.parse_args()
    if args.device == "cuda" and not torch.cuda.is_available():
        sys.exit("gpu.py: no CUDA GPU is available")
    record: dict[str, Any] = {
        "benchmark": "gpu", "config": {"scene": "blobs", "sizes": args.sizes, "cpu_sizes": args.cpu_sizes,
                                       "dualres_options": args.dualres_options, "paper_sizes": args.paper_sizes,
                                       "paper_epochs": args.paper_epochs, "paper_compile": args.paper_compile,
                                       "paper_options": args.paper_options},
        "machine": {"gpu": torch.cuda.get_device_name() if args.device == "cuda" else None, "torch": torch.__version__,
                    "python": platform.python_version(), "cpus": os.cpu_count(), "torch_threads": torch.get_num_threads()},
        "rows": [], "paper": [], "tests": None, "targets": None,
    }
    if args.tests:
        record["tests"] = cuda_tests()
        write_results(args.out, record)
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.data or Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        warm = capture_path(folder, (WARM_UP, WARM_UP), 0)
        for device in dict.fromkeys((args.device, *(("cpu",) if args.cpu_sizes else ()))):
            solve(warm, device, ["epochs=10"])
        # each section's numbers are written as soon as they are in: a run cut short keeps them
        record["rows"] = fast_rows(folder, args.device, args.sizes, args.cpu_sizes, args.dualres_options, args.profile, args.kernels,
                                   args.out)
        write_results(args.out, record)
        table(record["rows"])
        compiles = {"off": (False,), "on": (True,), "both": (False, True)}[args.paper_compile]
        for size in args.paper_sizes:
            for compiled in compiles:
                profile = args.out.parent / f"profile-paper-{size}{'-compiled' if compiled else ''}.txt" if "paper" in args.profile else None
                record["paper"].append(paper_row(folder, args.device, size, args.paper_epochs, args.paper_budget_s, compiled,
                                                 args.paper_options, profile))
                write_results(args.out, record)
    for paper in record["paper"]:
        if "error" in paper:
            print(f"\npaper {paper['size']} compile={paper['compile']}: failed: {paper['error'][:160]}")
            continue
        print(f"\npaper {paper['size']} compile={paper['compile']}: {paper['seconds_per_epoch'] * 1e3:.1f} ms/epoch, {PAPER_EPOCHS} epochs ≈ "
              f"{paper['projected_seconds']:.0f} s (target {PAPER_TARGET_S:g} s at 256²); MAE {paper['mae_deg']:.3f}° "
              f"(median {paper['median_deg']:.3f}°, p90 {paper['p90_deg']:.3f}°) after {paper['epochs_run']} epochs")
    record["targets"] = verdict(record["rows"], record["paper"])
    print("\ntargets:", json.dumps(record["targets"], indent=1))
    write_results(args.out, record)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
