"""Load time of ``pstoolkit view``'s page for a 256×256 result, in headless Chromium.

The result is the synthetic GGX sphere of ``pstoolkit.view.sample`` with all six maps (normal,
albedo, F0, roughness, error, depth: 3.4 MB of float32). Each run starts a fresh Chromium (new
profile, so nothing is cached) on the page and times, on the server's clock, from the request for
the page to the page's ``/ready`` beacon, sent once everything shown is drawn: the script, the index
and the maps fetched, the six panels drawn, the surface relit, the depth map splatted. Chromium's own
start-up comes before the request and is not counted. Also reported: the page's own clock at the
beacon (milliseconds since navigation began), one relighting of the 256² image in JavaScript (the
cost of a drag of the light), the server's start-up (reading the folder, encoding the maps) and the
bytes the page fetches. Cases: the whole page, and the relit canvas alone (``?view=relight``).
Prints a table and writes ``benchmarks/results/view.json``.

Target: the whole page drawn within 1 s of its request.

    python benchmarks/view.py [--size 256] [--runs 5]
"""

from __future__ import annotations

import argparse
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from results_io import write_results

from pstoolkit.view.headless import find_chromium, open_page
from pstoolkit.view.sample import write_sphere_result
from pstoolkit.view.server import ViewServer
from pstoolkit.view.source import load_result_folder

RESULTS = Path(__file__).resolve().parent / "results" / "view.json"
TARGET_S = 1.0
CASES = {"whole page": "", "relit canvas only": "?view=relight"}


def run_case(folder: Path, query: str, runs: int, chromium: str) -> dict[str, Any]:
    start = time.perf_counter()
    server = ViewServer(load_result_folder(folder)).start()
    startup_s = time.perf_counter() - start
    loads, page_ms, render_ms = [], [], []
    try:
        for _ in range(runs):
            server.requested.clear()
            server.ready.clear()
            server.ready_event.clear()
            with open_page(server.url + query, window=(1200, 1600), chromium=chromium):
                if not server.ready_event.wait(60.0) or not server.requested:
                    raise RuntimeError(f"the page never signalled it had drawn (errors: {server.page_errors})")
            ready_s, page, render = server.ready[0]
            loads.append(ready_s - server.requested[0])
            page_ms.append(page)
            render_ms.append(render)
        fetched = len(server.static["index.html"]) + len(server.index) + sum(len(b) for b in server.blobs.values())
        fetched += sum(len(server.static[name]) for name in server.static if name != "index.html")
    finally:
        server.close()
    return {
        "runs": runs,
        "load_s": loads,
        "load_median_s": statistics.median(loads),
        "load_max_s": max(loads),
        "page_ms_median": statistics.median(page_ms),
        "relight_ms_median": statistics.median(render_ms),
        "server_startup_s": startup_s,
        "bytes": fetched,
        "errors": server.page_errors,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--runs", type=int, default=5)
    args = parser.parse_args()
    chromium = find_chromium()
    if chromium is None:
        sys.exit("no Chromium binary: apt-get install chromium (or name one in $PSTOOLKIT_CHROMIUM)")
    version = subprocess.run([chromium, "--version"], capture_output=True, text=True).stdout.strip()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "sphere"
        write_sphere_result(folder, args.size)
        rows = {name: run_case(folder, query, args.runs, chromium) for name, query in CASES.items()}
    print(f"{args.size}×{args.size} GGX result, six maps; {args.runs} cold loads each ({version})")
    print(f"{'case':20s} {'median s':>9s} {'max s':>7s} {'page ms':>8s} {'relight ms':>11s} {'start-up s':>11s} {'MB':>6s}")
    for name, row in rows.items():
        print(f"{name:20s} {row['load_median_s']:9.3f} {row['load_max_s']:7.3f} {row['page_ms_median']:8.0f} "
              f"{row['relight_ms_median']:11.1f} {row['server_startup_s']:11.3f} {row['bytes'] / 1e6:6.2f}")
    worst = rows["whole page"]["load_max_s"]
    print(f"target: whole page drawn < {TARGET_S:g} s after its request: slowest run {worst:.3f} s ({'met' if worst < TARGET_S else 'MISSED'})")
    write_results(RESULTS, {
        "machine": {"python": platform.python_version(), "numpy": np.__version__, "processor": platform.processor() or platform.machine(),
                    "chromium": version},
        "config": {"size": args.size, "runs": args.runs, "maps": ["normal", "albedo", "f0", "roughness", "error", "depth"]},
        "rows": rows,
        "target_s": TARGET_S,
    })
    print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
