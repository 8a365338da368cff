"""Shared builders, from test_batch.py."""

from __future__ import annotations

from pathlib import Path

import pytest

from pstoolkit.sim.config import SimulationConfig
from pstoolkit.sim.simulator import simulate

SIZE = 32


def session_captures(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """Three 32 px hybrid captures (frames and events) of different scenes and seeds, simulated once
    per test session for every module that asks (a module-level fixture would simulate per module)."""
    folder = tmp_path_factory.getbasetemp() / "batch-captures"
    scenes = (("ball", "sphere", 0), ("blobs", "blobs", 1), ("relief", "relief", 2))
    paths = [folder / f"{name}.h5" for name, _, _ in scenes]
    folder.mkdir(exist_ok=True)
    for path, (_, scene, seed) in zip(paths, scenes):
        if not path.is_file():
            simulate(SimulationConfig(scene=scene, size=SIZE, seed=seed), path)
    return paths
