"""Shared builders, from test_replay.py."""

from __future__ import annotations

from pathlib import Path

import numpy as np

import psfmt
from pstoolkit.optics.lights import RingLight

PERIOD_US = 6000


def write_recording(path: Path, size: int = 32, periods: int = 2, frames_per_period: int = 6, seed: int = 0) -> Path:
    """A Lambertian sphere under a ``ring`` light (45°, ``PERIOD_US``): long-exposure uint8 frames
    integrated over 32 instants per window (attached shadows exact), seeded random events at half
    resolution, calibration and ground truth."""
    rng = np.random.default_rng(seed)
    light = RingLight(elevation_deg=45.0, period_us=PERIOD_US)
    c = (size - 1) / 2.0
    v, u = np.mgrid[0:size, 0:size].astype(np.float64)
    x, y = (u - c) / (c + 0.5), (c - v) / (c + 0.5)
    mask = x * x + y * y < 0.95
    z = np.sqrt(np.clip(1.0 - x * x - y * y, 0.0, None))
    normal = np.stack([x, y, z], axis=-1) * mask[..., None]
    normal[mask] /= np.linalg.norm(normal[mask], axis=-1, keepdims=True)
    k = periods * frames_per_period
    edges = np.round(np.arange(k + 1) * PERIOD_US / frames_per_period).astype(np.int64)
    instants = edges[:-1, None] + (np.arange(32) + 0.5)[None] * (np.diff(edges)[:, None] / 32.0)
    directions, _ = light.evaluate(instants.reshape(-1))
    shading = np.clip(np.einsum("hwx,tx->thw", normal, directions), 0.0, None).reshape(k, 32, size, size).mean(axis=1)
    albedo = np.array([0.9, 0.7, 0.5])
    images = shading[..., None] * albedo
    frames = np.rint(images / images.max() * 0.8 * 255).astype(np.uint8)
    n_events = 3000
    events = psfmt.EventArray(
        x=rng.integers(0, size // 2, n_events),
        y=rng.integers(0, size // 2, n_events),
        t=np.sort(rng.integers(0, periods * PERIOD_US, n_events)),
        p=rng.choice([-1, 1], n_events),
    )
    capture = psfmt.Capture(
        frames=psfmt.Frames(frames, t_start_us=edges[:-1], t_end_us=edges[1:]),
        events=psfmt.Events(size // 2, size // 2, events),
        lights=light.to_spec(),
        calibration=psfmt.Calibration(
            event_to_frame=psfmt.scale_affine(0.5), contrast_pos=0.15, contrast_neg=0.15, refractory_us=2000.0
        ),
        ground_truth=psfmt.GroundTruth(normal=normal, mask=mask),
    )
    return psfmt.write(capture, path)
