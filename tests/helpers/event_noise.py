"""Sensor noise added to a simulated capture's events, for the solvers' robustness tests and the
eventps measurements: background activity (uniform over pixels and time, random polarity), hot
pixels firing at a high rate, and a calibration whose thresholds differ per polarity from the ones
the events were fired with. Test helpers only: the product's simulators model their own noise."""

from __future__ import annotations

import copy
from dataclasses import replace

import numpy as np

import psfmt


def noise_events(capture: psfmt.Capture, *, background_hz: float, hot_pixels: int, hot_hz: float,
                 seed: int) -> psfmt.EventArray:
    """Noise events over the span of ``capture``'s events: ``background_hz`` per pixel at uniform
    random pixels, times and polarities, and ``hot_pixels`` random pixels each firing ``hot_hz``
    (uniform times, random polarity); sorted by time."""
    events = capture.events
    assert events is not None
    stream = events.read()
    t0, t1 = int(stream.t[0]), int(stream.t[-1])
    span_s = (t1 - t0) * 1e-6
    rng = np.random.default_rng(seed)
    n_background = rng.poisson(background_hz * span_s * events.width * events.height)
    x = rng.integers(0, events.width, n_background)
    y = rng.integers(0, events.height, n_background)
    hot = rng.choice(events.width * events.height, hot_pixels, replace=False)
    n_hot = rng.poisson(hot_hz * span_s, hot_pixels)
    x = np.concatenate([x, np.repeat(hot % events.width, n_hot)])
    y = np.concatenate([y, np.repeat(hot // events.width, n_hot)])
    t = rng.integers(t0, t1 + 1, len(x))
    p = rng.choice(np.array([-1, 1], np.int8), len(x))
    order = np.argsort(t, kind="stable")
    return psfmt.EventArray(x=x[order], y=y[order], t=t[order], p=p[order])


def with_noise(capture: psfmt.Capture, *, background_hz: float = 0.0, hot_pixels: int = 0, hot_hz: float = 0.0,
               contrast_pos: float | None = None, contrast_neg: float | None = None, seed: int = 0) -> psfmt.Capture:
    """A copy of ``capture`` whose events are its own merged with ``noise_events`` and whose
    calibration states ``contrast_pos``/``contrast_neg`` where given (a per-polarity mismatch between
    the thresholds the events fired with and the ones a solver is told)."""
    stream = capture.events.read()
    noise = noise_events(capture, background_hz=background_hz, hot_pixels=hot_pixels, hot_hz=hot_hz, seed=seed)
    merged = psfmt.EventArray.concatenate([stream, noise])
    order = np.argsort(merged.t, kind="stable")
    noisy = copy.copy(capture)
    noisy.events = psfmt.Events(width=capture.events.width, height=capture.events.height, data=merged[order])
    cal = capture.calibration
    noisy.calibration = replace(cal, contrast_pos=cal.contrast_pos if contrast_pos is None else contrast_pos,
                                contrast_neg=cal.contrast_neg if contrast_neg is None else contrast_neg)
    return noisy
