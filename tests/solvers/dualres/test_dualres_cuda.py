"""``dualres`` on a CUDA GPU gives what it gives on the CPU (skipped without one: ``pytest -m cuda``,
``benchmarks/gpu.py --tests``): the same capture, the same options, normals and MAE within float32
rounding of the different kernels' summation orders."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import psfmt
from pstoolkit.evaluation.metrics import angular_error_deg
from pstoolkit.plugin.manager import get_registries
from pstoolkit.solve.base import SolverResult, run_solver

pytestmark = pytest.mark.cuda


def _solve(capture: psfmt.Capture, device: str, *assignments: str) -> SolverResult:
    entry = get_registries().solvers.get("dualres")
    return run_solver(entry, capture, entry.parse_options(list(assignments)), device=device)[0]


@pytest.mark.parametrize("assignments", [("epochs=40",), ("preset=paper", "epochs=8")], ids=["fast", "paper"])
def test_cuda_and_cpu_give_the_same_normals(blobs_48: Path, assignments: tuple[str, ...]) -> None:
    capture = psfmt.load(blobs_48)
    cpu, gpu = (_solve(capture, device, *assignments) for device in ("cpu", "cuda"))
    truth = capture.ground_truth
    assert np.array_equal(cpu.mask, gpu.mask)
    apart = angular_error_deg(gpu.normal, cpu.normal, cpu.mask)[cpu.mask]
    mae_cpu, mae_gpu = (float(angular_error_deg(r.normal, truth.normal, truth.mask)[truth.mask].mean()) for r in (cpu, gpu))
    assert abs(mae_gpu - mae_cpu) <= 0.02
    assert np.percentile(apart, 90) <= 0.1
    assert gpu.diagnostics["device"] == "cuda"
