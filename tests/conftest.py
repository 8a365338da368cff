"""Captures several test modules share, simulated once per test session."""

from __future__ import annotations

from pathlib import Path

import pytest

from pstoolkit.sim.config import SimulationConfig
from pstoolkit.sim.simulator import simulate

pytest_plugins = ["pstoolkit.testing"]


@pytest.fixture(scope="session")
def sphere_48(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The default GGX sphere at 48 px (refractory 2 ms: no cast-shadow mask; its rim has two
    effective lights)."""
    path = tmp_path_factory.mktemp("sphere_48") / "sphere.h5"
    simulate(SimulationConfig(scene="sphere", size=48, seed=0), path)
    return path


@pytest.fixture(scope="session")
def blobs_48(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The default GGX blobs at 48 px (cast shadows; refractory 2 ms, reset-at-end)."""
    path = tmp_path_factory.mktemp("blobs_48") / "blobs.h5"
    simulate(SimulationConfig(scene="blobs", size=48, seed=0), path)
    return path
