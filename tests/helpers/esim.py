"""Shared builders, from test_esim.py."""

from __future__ import annotations

import numpy as np

from psfmt import EventArray
from pstoolkit.events.rule import log_irradiance, reference_time_us

SIZE = 16


PERIOD_US = 1_000_000.0


C = 0.15


def sine_scene(seed: int = 0, static_columns: int = 0) -> tuple:
    """I(x, t) = a(x)·(b(x) + s(x)·sin(2πt/T + φ(x))): per-pixel albedo, offset and phase; s = 0 on
    the first ``static_columns`` columns, 1 elsewhere."""
    rng = np.random.default_rng(seed)
    albedo = rng.uniform(0.3, 1.0, (SIZE, SIZE))
    offset = rng.uniform(1.2, 2.0, (SIZE, SIZE))
    phase = rng.uniform(0.0, 2 * np.pi, (SIZE, SIZE))
    swing = np.ones((SIZE, SIZE))
    swing[:, :static_columns] = 0.0

    def irradiance(t_us: np.ndarray) -> np.ndarray:
        t = np.asarray(t_us, dtype=np.float64)[:, None, None]
        return albedo * (offset + swing * np.sin(2 * np.pi * t / PERIOD_US + phase))

    return irradiance, albedo, offset, phase


def true_log(render, events: EventArray, t_us: np.ndarray) -> np.ndarray:
    """L at each event's own pixel and the given times (µs)."""
    frames = log_irradiance(render(np.asarray(t_us, dtype=np.float64)))
    return frames[np.arange(len(t_us)), events.y, events.x]


def threshold_residuals(render, events: EventArray, t0: float, refractory_us: float) -> np.ndarray:
    """L(t_k) − L_ref,k − p_k·C for every event, with the reference of the documented rule."""
    pixel = events.y.astype(np.int64) * SIZE + events.x
    order = np.argsort(pixel, kind="stable")
    ev = events[order]
    first = np.ones(len(ev), dtype=bool)
    first[1:] = pixel[order][1:] != pixel[order][:-1]
    ref_time = np.full(len(ev), float(t0))
    ref_time[~first] = reference_time_us(ev.t[:-1][~first[1:]], refractory_us)
    level = true_log(render, ev, ev.t.astype(np.float64))
    reference = true_log(render, ev, ref_time)
    return level - reference - ev.p * C
