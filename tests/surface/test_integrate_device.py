"""The device copy of the orthographic integration (``pstoolkit.surface.integrate_device``, what a
solver on a GPU integrates with) held to the host's sparse solve (``integrate.integrate_normals``):
its operator is the host's normal matrix, its coarse levels the Galerkin products, its heights the
host's to 1e-6 px on odd sizes, holes, separate parts and noisy normals. Through torch on the CPU, and
on a GPU under ``-m cuda``."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pstoolkit.surface.integrate import integrate_normals, neighbour_pairs, normal_matrix
from pstoolkit.surface.integrate_device import GridOperator, integrate_normals_on, solve_grid
from pstoolkit.surface.shapes import sphere, two_planes

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.cuda)]


def _operator(height: int, width: int, seed: int) -> tuple[GridOperator, np.ndarray]:
    """A random operator on a grid with a masked-out block, and the same as a sparse matrix (the host's)."""
    rng = np.random.default_rng(seed)
    mask = np.ones((height, width), dtype=bool)
    mask[height // 3 : height // 2, width // 4 : width // 2] = False
    pairs = neighbour_pairs(mask)
    weight = rng.uniform(0.01, 1.0, pairs.first.size)
    matrix = normal_matrix(pairs, weight).toarray()
    wx, wy = np.zeros((height, width - 1)), np.zeros((height - 1, width))
    flat_wx, flat_wy = wx.reshape(-1), wy.reshape(-1)
    for lo, axis, w in zip(pairs.lo, pairs.axis, weight, strict=True):
        v, u = divmod(int(lo), width)
        if axis == 1:
            flat_wx[v * (width - 1) + u] = w
        else:
            flat_wy[v * width + u] = w
    # the pixels outside the mask keep only the screen: the grid's system holds them at 0
    full = np.zeros((height * width, height * width))
    inside = np.flatnonzero(mask)
    full[np.ix_(inside, inside)] = matrix
    outside = np.flatnonzero(~mask)
    full[outside, outside] = 1e-6
    operator = GridOperator(torch.as_tensor(wx), torch.as_tensor(wy), torch.full((height, width), 1e-6, dtype=torch.float64))
    return operator, full


def test_the_grid_operator_is_the_hosts_normal_matrix_and_its_coarse_levels_the_galerkin_products() -> None:
    operator, full = _operator(11, 14, 0)
    x = np.random.default_rng(1).normal(size=(11, 14))
    np.testing.assert_allclose(operator.apply(torch.as_tensor(x)).numpy().ravel(), full @ x.ravel(), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(operator.dense().numpy(), full, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(operator.diag().numpy().ravel(), np.diag(full), rtol=1e-12)
    # 2×2 aggregation of an 11×14 grid: 6×7 cells, the last row of cells half empty
    cell = (np.arange(11)[:, None] // 2) * 7 + np.arange(14)[None, :] // 2
    prolong = np.zeros((11 * 14, 6 * 7))
    prolong[np.arange(11 * 14), cell.ravel()] = 1.0
    np.testing.assert_allclose(operator.coarse().dense().numpy(), prolong.T @ full @ prolong, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("device", DEVICES)
def test_a_random_system_is_solved_to_the_tolerance(device: str) -> None:
    operator, full = _operator(37, 53, 2)
    operator = GridOperator(*(t.to(device) for t in (operator.wx, operator.wy, operator.diagonal)))
    rhs = np.random.default_rng(3).normal(size=(37, 53))
    x, iterations = solve_grid(operator, torch.as_tensor(rhs, device=device))
    assert iterations <= 40  # measured 21
    residual = np.linalg.norm(full @ x.cpu().numpy().ravel() - rhs.ravel()) / np.linalg.norm(rhs)
    assert residual <= 1e-10


def _noisy(normal: np.ndarray, mask: np.ndarray, seed: int) -> np.ndarray:
    noisy = normal + np.random.default_rng(seed).normal(0.0, 0.05, normal.shape)
    noisy /= np.linalg.norm(noisy, axis=-1, keepdims=True)
    return np.where(mask[..., None], noisy, 0.0)


@pytest.mark.parametrize("device", DEVICES)
def test_the_heights_are_the_hosts(device: str) -> None:
    ball = sphere(61, 27.0)
    planes = two_planes(48, 6.0, 0.5)
    holed = ball.mask.copy()
    holed[20:26, 30:33] = False
    apart = ball.mask & (np.arange(61)[None, :] % 30 != 0)  # three parts
    odd = np.zeros((45, 70, 3))
    odd[..., 2] = 1.0
    odd[5:40, 3:66] = _noisy(np.dstack([np.full((35, 63), 0.3), np.zeros((35, 63)), np.ones((35, 63))]), np.ones((35, 63), bool), 4)
    cases = [(ball.normal, ball.mask), (planes.normal, planes.mask), (ball.normal, holed), (_noisy(ball.normal, apart, 5), apart),
             (odd, np.any(odd[..., :2] != 0, axis=-1))]
    for normal, mask in cases:
        host = integrate_normals(normal, mask)
        there = integrate_normals_on(normal, mask, device)
        assert np.abs(there - host).max() < 1e-6
        assert np.all(there[~mask] == 0.0)


def test_bad_and_empty_input() -> None:
    with pytest.raises(ValueError, match="disagree"):
        integrate_normals_on(np.zeros((4, 5, 3)), np.ones((4, 4), bool), "cpu")
    np.testing.assert_array_equal(integrate_normals_on(np.zeros((4, 4, 3)), np.zeros((4, 4), bool), "cpu"), np.zeros((4, 4)))


def test_a_capture_cuda_refuses_leaves_the_cycle_eager(monkeypatch: pytest.MonkeyPatch) -> None:
    """``_replayed`` with CUDA's capture stood in for on the CPU, refusing: the cycle itself comes back,
    the garbage collector was off during the capture and is on again."""
    import contextlib
    import gc
    from types import SimpleNamespace

    import pstoolkit.surface.integrate_device as integrate_device

    collecting: list[bool] = []

    @contextlib.contextmanager
    def refused(graph: object):  # type: ignore[no-untyped-def]
        collecting.append(gc.isenabled())
        yield
        raise RuntimeError("CUDA error: operation not permitted when stream is capturing")

    stream = SimpleNamespace(wait_stream=lambda other: None)
    monkeypatch.setattr(torch.cuda, "Stream", lambda device=None: stream)
    monkeypatch.setattr(torch.cuda, "current_stream", lambda device=None: stream)
    monkeypatch.setattr(torch.cuda, "stream", lambda chosen: contextlib.nullcontext())
    monkeypatch.setattr(torch.cuda, "CUDAGraph", object)
    monkeypatch.setattr(torch.cuda, "graph", refused)
    operator, _ = _operator(37, 53, 2)
    cycle = integrate_device.VCycle(operator)
    assert integrate_device._replayed(cycle, torch.zeros(37, 53, dtype=torch.float64)) is cycle
    assert collecting == [False] and gc.isenabled()


@pytest.mark.cuda
def test_on_cuda_the_cycle_is_replayed_as_a_graph_and_solves_as_the_eager_one(monkeypatch: pytest.MonkeyPatch) -> None:
    import pstoolkit.surface.integrate_device as integrate_device

    operator, full = _operator(37, 53, 2)
    operator = GridOperator(*(t.to("cuda") for t in (operator.wx, operator.wy, operator.diagonal)))
    rhs = torch.as_tensor(np.random.default_rng(3).normal(size=(37, 53)), device="cuda")
    replays: list[int] = []
    replay = torch.cuda.CUDAGraph.replay
    monkeypatch.setattr(torch.cuda.CUDAGraph, "replay", lambda self: replays.append(1) or replay(self))
    x, iterations = solve_grid(operator, rhs)
    assert len(replays) == iterations
    monkeypatch.setattr(integrate_device, "_replayed", lambda cycle, like: cycle)
    eager, eager_iterations = solve_grid(operator, rhs)
    assert eager_iterations == iterations
    torch.testing.assert_close(x, eager, rtol=1e-12, atol=1e-12)
    assert np.linalg.norm(full @ x.cpu().numpy().ravel() - rhs.cpu().numpy().ravel()) / float(torch.linalg.vector_norm(rhs)) <= 1e-10
