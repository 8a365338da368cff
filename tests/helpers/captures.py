"""Shared builders, from test_format_roundtrip.py."""

from __future__ import annotations

from typing import Any

import numpy as np

import psfmt

FRAME_SIZE = 64


SENSOR_SIZE = 32


PERIOD_US = 30_000


CREATED = "2025-01-02T03:04:05+00:00"


def sample_events(n: int, seed: int, *, width: int = SENSOR_SIZE, height: int = SENSOR_SIZE,
                  span_us: int = PERIOD_US) -> psfmt.EventArray:
    """``n`` events sorted over [0, span_us) µs on a width×height sensor."""
    rng = np.random.default_rng(seed)
    return psfmt.EventArray(
        x=rng.integers(0, width, n),
        y=rng.integers(0, height, n),
        t=np.sort(rng.integers(0, span_us, n)),
        p=rng.choice([-1, 1], n),
    )


def sample_capture(kind: str, seed: int = 0, *, n_events: int = 5000, dtype: Any = np.uint8) -> psfmt.Capture:
    """A small capture of ``kind``: ``hybrid`` (3 long exposures + events under a ring light),
    ``events`` (events only), ``frames`` (DiLiGenT-style: per-frame instantaneous lights)."""
    rng = np.random.default_rng(seed)
    h = w = FRAME_SIZE
    normal = rng.normal(size=(h, w, 3))
    normal[..., 2] = np.abs(normal[..., 2]) + 1.0
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    gt = psfmt.GroundTruth(
        normal=normal.astype(np.float32),
        mask=rng.random((h, w)) > 0.2,
        albedo=rng.random((h, w, 3)).astype(np.float32),
        depth=rng.random((h, w)).astype(np.float32),
        materials={"roughness": rng.random((h, w)).astype(np.float32), "f0": rng.random((h, w, 3)).astype(np.float32)},
    )
    result = psfmt.Result(
        name="eventps",
        maps={"normal": normal.astype(np.float32), "albedo": rng.random((h, w, 3)).astype(np.float32)},
        solver="eventps",
        options={"threshold": 0.15, "epochs": 3, "shadow": "events"},
        seconds=1.25,
        version="0.1.0",
        created=CREATED,
    )
    common: dict[str, Any] = {
        "description": f"{kind} sample, seed {seed}",
        "creator": "tests",
        "creator_version": "9.9",
        "created": CREATED,
        "ground_truth": gt,
        "results": {"eventps": result},
    }
    ring = psfmt.LightSpec(
        "ring",
        {"elevation_deg": 43.0, "period_us": PERIOD_US, "phase_deg": 90.0, "sense": -1,
         "intensity": np.array([1.0, 0.9, 0.8]), "t0_us": 0},
    )
    calibration = psfmt.Calibration(
        event_to_frame=psfmt.scale_affine(SENSOR_SIZE / FRAME_SIZE),
        contrast_pos=0.15,
        contrast_neg=0.2,
        refractory_us=500.0,
        refractory_rule="rate-limited",
    )
    if kind == "frames":
        k = 6
        data = rng.random((k, h, w, 3)) * 0.9
        data = (data * np.iinfo(dtype).max).astype(dtype) if np.dtype(dtype).kind == "u" else data.astype(dtype)
        directions = rng.normal(size=(k, 3))
        directions[:, 2] = np.abs(directions[:, 2]) + 1
        directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
        frames = psfmt.Frames(data, light_direction=directions, light_intensity=rng.random((k, 3)) + 0.5,
                              bit_depth=16 if np.dtype(dtype) == np.uint16 else None)
        return psfmt.Capture(frames=frames, **common)
    events = psfmt.Events(SENSOR_SIZE, SENSOR_SIZE, sample_events(n_events, seed))
    triggers = psfmt.Triggers(t=[0, PERIOD_US // 2], channel=[0, 1], value=[1, 0])
    if kind == "events":
        return psfmt.Capture(events=events, triggers=triggers, lights=ring, calibration=calibration, **common)
    third = PERIOD_US // 3
    frames = psfmt.Frames(
        rng.integers(0, 250, (3, h, w, 3)).astype(np.uint8),
        t_start_us=[0, third, 2 * third],
        t_end_us=[third, 2 * third, PERIOD_US],
    )
    return psfmt.Capture(frames=frames, events=events, triggers=triggers, lights=ring, calibration=calibration, **common)
