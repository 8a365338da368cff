"""Shared builders, from test_calibrate.py."""

from __future__ import annotations

from pathlib import Path

import numpy as np

import psfmt
from pstoolkit.hardware.calibrate import (
    apply_affine,
)

# event → frame: about 2× (a half-resolution event sensor), rotated 2°, slightly sheared, shifted
TRUE_AFFINE = np.array([[2.03 * np.cos(0.035), -2.03 * np.sin(0.035), 1.3], [2.01 * np.sin(0.035) + 0.02, 2.01 * np.cos(0.035), -0.8]])


def _gaussians(shape: tuple[int, int], centres: np.ndarray, sigma: float, peak: float) -> np.ndarray:
    v, u = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    d2 = (u[..., None] - centres[:, 0]) ** 2 + (v[..., None] - centres[:, 1]) ** 2
    return peak * np.exp(-0.5 * d2 / sigma**2).sum(axis=-1)


def led_target(path: Path, seed: int = 0) -> Path:
    """A 5×5 LED array (slightly irregular) seen by a 64 px frame camera and a 32 px event camera
    through ``TRUE_AFFINE``, plus a reflection only the frame sees and a hot pixel only the events
    have."""
    rng = np.random.default_rng(seed)
    gu, gv = np.meshgrid(np.linspace(12, 50, 5), np.linspace(11, 49, 5))
    leds_frame = np.stack([gu.ravel(), gv.ravel()], axis=1) + rng.uniform(-0.8, 0.8, (25, 2))
    inverse = np.linalg.inv(np.vstack([TRUE_AFFINE, [0, 0, 1]]))[:2]
    leds_event = apply_affine(inverse, leds_frame)
    grey = _gaussians((64, 64), np.vstack([leds_frame, [[57.0, 4.0]]]), 1.3, 200.0) + rng.normal(0.0, 0.5, (64, 64))
    frames = np.clip(np.rint(np.repeat(grey[None, ..., None], 3, axis=-1)[[0, 0]] + 5), 0, 255).astype(np.uint8)
    counts = np.rint(_gaussians((32, 32), leds_event, 0.8, 40.0)).astype(np.int64)
    counts[2, 29] += 30  # a hot pixel
    y, x = np.divmod(np.repeat(np.arange(32 * 32), counts.ravel()), 32)
    t = np.sort(rng.integers(0, 20000, len(x)))
    events = psfmt.EventArray(x=x, y=y, t=t, p=np.where(np.arange(len(x)) % 2 == 0, 1, -1))
    capture = psfmt.Capture(
        frames=psfmt.Frames(frames, t_start_us=[0, 10000], t_end_us=[10000, 20000]),
        events=psfmt.Events(32, 32, events),
        ground_truth=psfmt.GroundTruth(mask=np.ones((64, 64), bool)),
    )
    return psfmt.write(capture, path)
