"""The ``flat`` solver: the normal (0, 0, 1) everywhere, inside a mask of the pixels that saw light.

It is the smallest real solver (a baseline any method must beat) and shows the interface: class
attributes for the registry, typed options, and ``solve`` returning a ``SolverResult``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

import psfmt
from pstoolkit import Option, Progress, Solver, SolverResult, UserError


def frames_mask(frames: psfmt.Frames, threshold: float, progress: Progress) -> np.ndarray:
    """Pixels whose brightest frame (any channel) exceeds ``threshold`` × saturation."""
    peak = np.zeros((frames.height, frames.width), dtype=np.float32)
    for k in range(frames.count):  # one frame at a time: frames may be a lazy on-disk stack
        np.maximum(peak, frames.as_float(k).max(axis=-1), out=peak)
        progress((k + 1) / frames.count, "frames")
    return peak > threshold


def events_mask(events: psfmt.Events, min_events: int, size: tuple[int, int], progress: Progress) -> np.ndarray:
    """Pixels that fired at least ``min_events`` events, resampled (nearest) to ``size`` = (H, W);
    assumes the event sensor sees the same field of view as the target grid."""
    counts = np.zeros(events.height * events.width, dtype=np.int64)
    done, total = 0, max(len(events), 1)
    for chunk in events.chunks():
        counts += np.bincount(chunk.y.astype(np.int64) * events.width + chunk.x, minlength=counts.size)
        done += len(chunk)
        progress(done / total, "events")
    fired = counts.reshape(events.height, events.width) >= min_events
    h, w = size
    rows = np.arange(h) * events.height // h
    cols = np.arange(w) * events.width // w
    return fired[np.ix_(rows, cols)]


class FlatSolver(Solver):
    name = "flat"
    summary = "normal (0, 0, 1) everywhere inside the mask of lit pixels (a baseline and a template)"
    options = (
        Option(
            "threshold", float, 0.05, "inside when the brightest frame exceeds this fraction of saturation",
            minimum=0.0, maximum=1.0,
        ),
        Option("min_events", int, 1, "without frames: inside when a pixel fired at least this many events", minimum=1),
    )

    def solve(self, capture: psfmt.Capture, options: dict[str, Any], progress: Progress) -> SolverResult:
        h, w = psfmt.target_size(capture)
        if capture.frames is not None:
            mask = frames_mask(capture.frames, options["threshold"], progress)
        elif capture.events is not None:
            mask = events_mask(capture.events, options["min_events"], (h, w), progress)
        else:
            raise UserError(f"solver {self.name!r} needs frames or events, but {capture.path or 'the capture'} has neither")
        normal = np.zeros((h, w, 3), dtype=np.float32)
        normal[..., 2] = 1.0
        return SolverResult(normal=normal, mask=mask, diagnostics={"mask_pixels": int(mask.sum())})
