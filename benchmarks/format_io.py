"""Write and read speed of the hybrid-capture format (spec/hybrid-capture.md).

Writes 10 M events (sorted times over about 1 s, random pixels on a 1280×720 sensor, ±1 polarity)
and three 2048×2448×3 uint8 frames to a temporary folder, then reads them back: all events at once
and in bounded-memory chunks (each the median of three runs on a freshly opened file), the frames,
and 1 ms event windows through the millisecond index (the median of many random windows on a freshly
opened file). Prints a table and writes ``benchmarks/results/format_io.json``.

Targets: full event read ≥ 20 M events/s; a 1 ms window read from a 10 M-event file < 5 ms.

    python benchmarks/format_io.py [--events 10000000] [--windows 500] [--seed 0]
"""

from __future__ import annotations

import argparse
import platform
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from results_io import write_results

import psfmt

RESULTS = Path(__file__).resolve().parent / "results" / "format_io.json"
SENSOR_W, SENSOR_H = 1280, 720
FRAME_H, FRAME_W = 2048, 2448
TARGET_EVENTS_PER_S = 20e6
TARGET_WINDOW_MS = 5.0
READ_REPEATS = 3


def make_events(n: int, duration_us: int, rng: np.random.Generator) -> psfmt.EventArray:
    """Sorted uniform times over ``duration_us``, uniform pixels, balanced polarity."""
    return psfmt.EventArray(
        x=rng.integers(0, SENSOR_W, n, dtype=np.uint16),
        y=rng.integers(0, SENSOR_H, n, dtype=np.uint16),
        t=np.sort(rng.integers(0, duration_us, n, dtype=np.int64)),
        p=rng.choice(np.array([-1, 1], dtype=np.int8), n),
    )


def make_frames(count: int, rng: np.random.Generator) -> np.ndarray:
    """Smooth shaded images with sensor noise: compressible like photographs, unlike white noise."""
    v, u = np.mgrid[0:FRAME_H, 0:FRAME_W].astype(np.float32)
    out = np.empty((count, FRAME_H, FRAME_W, 3), np.uint8)
    for k in range(count):
        phase = 2 * np.pi * k / count
        shade = 0.5 + 0.35 * np.cos(u / 300.0 + phase) * np.sin(v / 250.0 - phase)
        for c, gain in enumerate((1.0, 0.8, 0.6)):
            noise = rng.normal(0.0, 2.0, (FRAME_H, FRAME_W)).astype(np.float32)
            out[k, ..., c] = np.clip(255 * gain * shade + noise, 0, 255).astype(np.uint8)
    return out


def timed(fn: Callable[[], Any]) -> tuple[float, Any]:
    start = time.perf_counter()
    value = fn()
    return time.perf_counter() - start, value


def event_bytes(n: int) -> int:
    return n * (2 + 2 + 8 + 1)


def run(n_events: int, n_windows: int, seed: int, folder: Path) -> dict[str, Any]:
    rng = np.random.default_rng(seed)
    duration_us = 1_000_000
    events = make_events(n_events, duration_us, rng)
    frames = make_frames(3, rng)
    third = duration_us // 3
    ev_path, fr_path = folder / "events.h5", folder / "frames.h5"
    ev_capture = psfmt.Capture(events=psfmt.Events(SENSOR_W, SENSOR_H, events))
    fr_capture = psfmt.Capture(
        frames=psfmt.Frames(frames, t_start_us=[0, third, 2 * third], t_end_us=[third, 2 * third, duration_us])
    )
    ev_raw, fr_raw = event_bytes(n_events), frames.nbytes
    rows: dict[str, dict[str, float]] = {}

    seconds, _ = timed(lambda: psfmt.write(ev_capture, ev_path))
    rows["write events"] = {"s": seconds, "MB/s": ev_raw / seconds / 1e6, "Mev/s": n_events / seconds / 1e6}
    seconds, _ = timed(lambda: psfmt.write(fr_capture, fr_path))
    rows["write 3 frames"] = {"s": seconds, "MB/s": fr_raw / seconds / 1e6}

    whole, chunked = [], []
    for _ in range(READ_REPEATS):
        with psfmt.read(ev_path) as capture:
            seconds, full = timed(capture.events.read)
            assert len(full) == n_events and np.array_equal(full.t, events.t)
            whole.append(seconds)
            del full
        with psfmt.read(ev_path) as capture:
            seconds, count = timed(lambda: sum(len(block) for block in capture.events.chunks()))
            assert count == n_events
            chunked.append(seconds)
    for name, times in (("read events (whole)", whole), ("read events (chunks)", chunked)):
        seconds = float(np.median(times))
        rows[name] = {"s": seconds, "MB/s": ev_raw / seconds / 1e6, "Mev/s": n_events / seconds / 1e6}

    starts = rng.integers(0, duration_us - 1000, n_windows)
    with psfmt.read(ev_path) as capture:
        times, sizes = [], []
        for t0 in starts:
            seconds, window = timed(lambda t0=t0: capture.events.window(int(t0), int(t0) + 1000))
            times.append(seconds)
            sizes.append(len(window))
    lo, hi = np.searchsorted(events.t, [starts[-1], starts[-1] + 1000])
    assert sizes[-1] == hi - lo
    median = float(np.median(times))
    mean_size = float(np.mean(sizes))
    rows["read 1 ms window (median)"] = {
        "s": median,
        "MB/s": event_bytes(int(mean_size)) / median / 1e6,
        "Mev/s": mean_size / median / 1e6,
    }
    rows["read 1 ms window (first, cold)"] = {"s": times[0]}
    rows["read 1 ms window (p90)"] = {"s": float(np.percentile(times, 90))}

    with psfmt.read(fr_path) as capture:
        seconds, data = timed(lambda: np.asarray(capture.frames.data))
        assert np.array_equal(data, frames)
        rows["read 3 frames (whole)"] = {"s": seconds, "MB/s": fr_raw / seconds / 1e6}
        seconds, _ = timed(lambda: capture.frames.frame(1))
        rows["read 1 frame"] = {"s": seconds, "MB/s": fr_raw / 3 / seconds / 1e6}

    sizes_on_disk = {"events": ev_path.stat().st_size, "frames": fr_path.stat().st_size}
    return {
        "machine": {"python": platform.python_version(), "h5py": h5py.__version__, "hdf5": h5py.version.hdf5_version,
                    "processor": platform.processor() or platform.machine()},
        "config": {"events": n_events, "duration_us": duration_us, "sensor": [SENSOR_W, SENSOR_H],
                   "frames": [3, FRAME_H, FRAME_W, 3], "windows": n_windows, "seed": seed,
                   "mean_events_per_window": mean_size},
        "rows": rows,
        "size": {
            "events_raw_bytes": ev_raw,
            "events_file_bytes": sizes_on_disk["events"],
            "events_ratio": sizes_on_disk["events"] / ev_raw,
            "frames_raw_bytes": fr_raw,
            "frames_file_bytes": sizes_on_disk["frames"],
            "frames_ratio": sizes_on_disk["frames"] / fr_raw,
        },
        "targets": {
            "full_event_read_Mev_per_s": {"target": TARGET_EVENTS_PER_S / 1e6,
                                          "measured": rows["read events (whole)"]["Mev/s"]},
            "window_read_ms": {"target": TARGET_WINDOW_MS, "measured": median * 1e3},
        },
    }


def print_table(result: dict[str, Any]) -> None:
    print(f"{'operation':32s} {'time':>10s} {'MB/s':>9s} {'M ev/s':>9s}")
    for name, row in result["rows"].items():
        t = row["s"]
        time_text = f"{t * 1e3:8.3f} ms" if t < 1 else f"{t:8.3f} s "
        mbs = f"{row['MB/s']:9.1f}" if "MB/s" in row else f"{'':9s}"
        mev = f"{row['Mev/s']:9.2f}" if "Mev/s" in row else f"{'':9s}"
        print(f"{name:32s} {time_text:>10s} {mbs} {mev}")
    size = result["size"]
    for kind in ("events", "frames"):
        print(f"file size {kind:6s}: {size[f'{kind}_file_bytes'] / 1e6:8.1f} MB for {size[f'{kind}_raw_bytes'] / 1e6:8.1f} MB raw "
              f"({100 * size[f'{kind}_ratio']:.1f} %)")
    targets = result["targets"]
    read = targets["full_event_read_Mev_per_s"]
    window = targets["window_read_ms"]
    print(f"target full event read  ≥ {read['target']:.0f} M ev/s: {read['measured']:.1f} "
          f"({'met' if read['measured'] >= read['target'] else 'MISSED'})")
    print(f"target 1 ms window read < {window['target']:.0f} ms: {window['measured']:.3f} "
          f"({'met' if window['measured'] < window['target'] else 'MISSED'})")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--events", type=int, default=10_000_000)
    parser.add_argument("--windows", type=int, default=500)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="format_io_") as folder:
        result = run(args.events, args.windows, args.seed, Path(folder))
    print_table(result)
    write_results(RESULTS, result)
    print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
