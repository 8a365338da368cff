"""Speed of the ESIM-style event generator (``pstoolkit.sim.esim.simulate_events``).

A Lambertian sphere on a black background at 128×128 event pixels, lit by a light circling at 47°
zenith, one period of 33 333 µs (30 rounds/s), C = 0.15, rendered in numpy (one small matrix
product per batch, so the simulator's own cost dominates). Cases: with a 5 % ambient term (no pixel
goes dark, smooth log-irradiance), with attached shadows (each pixel leaving shadow jumps by
≈ 7 in ln(I + 1e-3), so the adaptive sampling refines down to ``min_dt_us``), the same with a
coarser ``min_dt_us``, with the 2 ms refractory of the semi-real recipe, and with per-pixel
refinement (``render_pixels``: only the pixels leaving shadow are rendered at the fine times, the
simulator's mode). Each case is run
``--repeat`` times and the fastest kept; seconds are wall-clock, with the render's share shown.
Prints a table and writes ``benchmarks/results/esim.json``.

Target: ≥ 5 M events/s end to end.

    python benchmarks/esim.py [--size 128] [--repeat 3]
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np
from results_io import write_results

from pstoolkit.sim.esim import simulate_events
from pstoolkit.sim.sensor import EventSensor

RESULTS = Path(__file__).resolve().parent / "results" / "esim.json"
PERIOD_US = 33_333.0
ZENITH_DEG = 47.0
TARGET_EVENTS_PER_S = 5e6
CASES: dict[str, dict[str, float]] = {
    "ambient 5 %": {"ambient": 0.05},
    "attached shadows": {"ambient": 0.0},
    "shadows, min_dt 10 µs": {"ambient": 0.0, "min_dt_us": 10.0},
    "shadows, refractory 2 ms": {"ambient": 0.0, "refractory_us": 2000.0},
    "shadows, per-pixel refinement": {"ambient": 0.0, "per_pixel": 1.0},
}


class SphereRender:
    """Grey irradiance of a white Lambertian sphere, max(0, n·l) + ambient, 0 off the sphere; counts
    render calls, samples and seconds."""

    def __init__(self, size: int, ambient: float) -> None:
        v, u = np.mgrid[0:size, 0:size].astype(np.float64)
        x = (u - (size - 1) / 2) / (0.475 * size)
        y = -(v - (size - 1) / 2) / (0.475 * size)
        self.inside = (x * x + y * y < 1).reshape(-1)
        z = np.sqrt(np.clip(1 - x * x - y * y, 0, 1))
        self.normals = np.stack([x, y, z]).reshape(3, -1) * self.inside
        self.size, self.ambient = size, ambient
        self.calls, self.samples, self.pixel_samples, self.seconds = 0, 0, 0, 0.0

    def _light(self, t_us: np.ndarray) -> np.ndarray:
        angle = 2 * np.pi * np.asarray(t_us, dtype=np.float64) / PERIOD_US
        zen = np.deg2rad(ZENITH_DEG)
        return np.stack([np.sin(zen) * np.cos(angle), np.sin(zen) * np.sin(angle), np.full_like(angle, np.cos(zen))], -1)

    def __call__(self, t_us: np.ndarray) -> np.ndarray:
        start = time.perf_counter()
        light = self._light(t_us)
        irradiance = np.maximum(light @ self.normals, 0.0)
        irradiance += self.ambient
        irradiance *= self.inside
        self.calls += 1
        self.samples += len(light)
        self.seconds += time.perf_counter() - start
        return irradiance.reshape(len(light), self.size, self.size)

    def pixels(self, t_us: np.ndarray, pixel: np.ndarray) -> np.ndarray:
        """Single pixels at single times (the ``render_pixels`` callback)."""
        start = time.perf_counter()
        shade = np.maximum(np.einsum("mx,xm->m", self._light(t_us), self.normals[:, pixel]), 0.0)
        out = (shade + self.ambient) * self.inside[pixel]
        self.pixel_samples += len(pixel)
        self.seconds += time.perf_counter() - start
        return out


def run_case(size: int, options: dict[str, float]) -> dict[str, Any]:
    render = SphereRender(size, options["ambient"])
    kwargs: dict[str, Any] = {"sensor": EventSensor(refractory_us=options.get("refractory_us", 0.0)),
                              "min_dt_us": options.get("min_dt_us", 1.0)}
    if options.get("per_pixel"):
        kwargs["render_pixels"] = render.pixels
    start = time.perf_counter()
    events = sum(len(chunk) for chunk in simulate_events(render, 0, PERIOD_US, width=size, height=size, **kwargs))
    seconds = time.perf_counter() - start
    return {
        "events": events,
        "s": seconds,
        "render_s": render.seconds,
        "samples": render.samples,
        "pixel_samples": render.pixel_samples,
        "render_calls": render.calls,
        "Mev/s": events / seconds / 1e6,
        "Mev/s_without_render": events / (seconds - render.seconds) / 1e6,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    rows = {}
    for name, options in CASES.items():
        runs = [run_case(args.size, options) for _ in range(args.repeat)]
        rows[name] = {**min(runs, key=lambda r: r["s"]), "options": options}
    print(f"{'case':30s} {'events':>9s} {'samples':>8s} {'pixels':>9s} {'s':>7s} {'render s':>9s} {'M ev/s':>7s} {'w/o render':>10s}")
    for name, row in rows.items():
        print(f"{name:30s} {row['events']:9d} {row['samples']:8d} {row['pixel_samples']:9d} {row['s']:7.3f} {row['render_s']:9.3f} "
              f"{row['Mev/s']:7.2f} {row['Mev/s_without_render']:10.2f}")
    best = max(row["Mev/s"] for row in rows.values())
    print(f"target ≥ {TARGET_EVENTS_PER_S / 1e6:.0f} M ev/s end to end: best case {best:.2f} "
          f"({'met' if best >= TARGET_EVENTS_PER_S / 1e6 else 'MISSED'})")
    result = {
        "machine": {"python": platform.python_version(), "numpy": np.__version__,
                    "processor": platform.processor() or platform.machine()},
        "config": {"size": args.size, "period_us": PERIOD_US, "contrast": 0.15, "repeat": args.repeat},
        "rows": rows,
        "target_Mev_per_s": TARGET_EVENTS_PER_S / 1e6,
    }
    write_results(RESULTS, result)
    print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
