"""Captures several test modules share, simulated once per test session."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from pstoolkit.sim.config import SimulationConfig
from pstoolkit.sim.simulator import simulate

pytest_plugins = ["pstoolkit.testing"]


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Tests marked ``cuda`` are skipped where torch sees no CUDA GPU (CI has none)."""
    if torch.cuda.is_available():
        return
    skip = pytest.mark.skip(reason="needs a CUDA GPU")
    for item in items:
        if item.get_closest_marker("cuda") is not None:
            item.add_marker(skip)


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
