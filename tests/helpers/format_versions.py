"""Captures as earlier versions of psfmt wrote them: the files in ``tests/psfmt/data`` (made by
``tests/psfmt/data/make_old_versions.py`` with the psfmt of format 1.0 and 1.1) and the capture each holds."""

from __future__ import annotations

from pathlib import Path

import numpy as np

import psfmt

DATA = Path(__file__).resolve().parents[1] / "psfmt" / "data"
CREATED = "2025-01-02T03:04:05+00:00"
OLD_VERSIONS = ("1.0", "1.1")


def old_file(version: str) -> Path:
    """The capture file the psfmt of format ``version`` ("1.0" or "1.1") wrote."""
    return DATA / f"hybrid-{version}.h5"


def old_capture(version: str) -> psfmt.Capture:
    """The small hybrid capture in ``old_file(version)``: 2 frames of 8×8 RGB, 200 events of a 4×4
    sensor, triggers, a ring light, an orthographic calibration (with ``refractory_rule`` from 1.1
    on), ground truth and one result. Only parameters every psfmt since 1.0 takes are used."""
    rng = np.random.default_rng(11)
    h = w = 8
    normal = np.zeros((h, w, 3), np.float32)
    normal[..., 2] = 1.0
    t = np.sort(rng.integers(0, 3000, 200))
    events = psfmt.EventArray(rng.integers(0, 4, 200), rng.integers(0, 4, 200), t, rng.choice([-1, 1], 200))
    calibration = psfmt.Calibration(event_to_frame=psfmt.scale_affine(0.5), contrast_pos=0.15, contrast_neg=0.2, refractory_us=100.0)
    if version != "1.0":
        calibration.refractory_rule = "rate-limited"
    return psfmt.Capture(
        frames=psfmt.Frames(rng.integers(0, 250, (2, h, w, 3)).astype(np.uint8), t_start_us=[0, 1500], t_end_us=[1500, 3000]),
        events=psfmt.Events(4, 4, events),
        triggers=psfmt.Triggers(t=[0, 1500], channel=[0, 1], value=[1, 0]),
        lights=psfmt.LightSpec("ring", {"elevation_deg": 43.0, "period_us": 3000, "phase_deg": 90.0, "sense": -1,
                                        "intensity": np.array([1.0, 0.9, 0.8]), "t0_us": 0}),
        calibration=calibration,
        ground_truth=psfmt.GroundTruth(normal=normal, mask=np.ones((h, w), bool), depth=rng.random((h, w)).astype(np.float32)),
        results={"eventps": psfmt.Result("eventps", {"normal": normal}, solver="eventps", options={"epochs": 3},
                                         seconds=1.25, version="0.1.0", created=CREATED)},
        description=f"written by the psfmt of format {version}",
        creator="tests",
        creator_version="9.9",
        created=CREATED,
    )
