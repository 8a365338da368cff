"""``integrate_normals`` on a torch device: the same least-squares problem (``integrate``'s module
docstring), solved by conjugate gradients preconditioned with a multigrid V-cycle on the pixel grid.

The system lives on the whole (H, W) grid: a pixel outside the mask has no pairs, only the screen,
so its height stays 0. The operator is a weighted graph Laplacian plus a diagonal, stored as its
horizontal and vertical pair weights and the diagonal, and applied with shifted slices. Each coarser
level merges 2×2 cells (piecewise-constant aggregation), whose Galerkin operator is again such a
grid: the weight between two merged cells is the sum of the weights of the pairs between them, the
diagonal the sum of theirs. The V-cycle smooths with damped Jacobi before and after the coarse
correction (symmetric, as conjugate gradients need) and solves the coarsest level by its inverse (from
its Cholesky factor: a product, which a CUDA graph can hold).

On CUDA the V-cycle is captured once a solve as a CUDA graph and replayed at every iteration
(``_replayed``): it is hundreds of small operations (539 on 5 levels at 256², 807 on 7 at 1024²), whose
launches one by one, not their work, set its time at such sizes, and a surface takes some 18 cycles. A
capture CUDA refuses leaves the cycle eager.

In float64 to ``integrate.MULTIGRID_TOL``, the tolerance of the host's multigrid: heights to within
1e-6 px of the host's at 1024². A sparse factorisation has no counterpart on a GPU; the host's
pyamg set-up and solve took 8 s a surface at 1024² on one core.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from pstoolkit._shared import devices
from pstoolkit.surface.integrate import MULTIGRID_TOL, SCREEN, surface_gradients

# Cells on the coarsest level's side, solved directly.
COARSEST = 16
# Damped Jacobi: sweeps before and after the coarse correction, and the damping.
SWEEPS = 2
DAMPING = 0.7
# Piecewise-constant aggregation over-corrects smooth errors by about this factor's inverse.
COARSE_SCALE = 1.8
MAX_ITERATIONS = 500


@dataclass
class GridOperator:
    """``wx`` (H, W − 1) weights of the horizontal pairs, ``wy`` (H − 1, W) of the vertical ones (0 where
    a pair leaves the mask), ``diagonal`` (H, W) of the screen: A·x = Σ pairs w·(x_a − x_b) + diagonal·x."""

    wx: Tensor
    wy: Tensor
    diagonal: Tensor

    def apply(self, x: Tensor) -> Tensor:
        """A·x for x (H, W)."""
        out = self.diagonal * x
        flow = self.wx * (x[:, 1:] - x[:, :-1])
        out[:, 1:] += flow
        out[:, :-1] -= flow
        flow = self.wy * (x[1:] - x[:-1])
        out[1:] += flow
        out[:-1] -= flow
        return out

    def diag(self) -> Tensor:
        """The diagonal of A (H, W)."""
        out = self.diagonal.clone()
        out[:, 1:] += self.wx
        out[:, :-1] += self.wx
        out[1:] += self.wy
        out[:-1] += self.wy
        return out

    def coarse(self) -> GridOperator:
        """The Galerkin operator Pᵀ·A·P of 2×2 aggregation (the grid padded to even sides)."""
        h, w = self.diagonal.shape
        hc, wc = (h + 1) // 2, (w + 1) // 2
        diagonal = _pool(self.diagonal, hc, wc)
        # the pairs between cell columns 2j+1 and 2j+2 join coarse columns j and j+1
        wx = _pad(self.wx, 2 * hc, 2 * wc - 1)[:, 1::2][:, : wc - 1]
        wx = wx[0::2] + wx[1::2]
        wy = _pad(self.wy, 2 * hc - 1, 2 * wc)[1::2][: hc - 1]
        wy = wy[:, 0::2] + wy[:, 1::2]
        return GridOperator(wx, wy, diagonal)

    def dense(self) -> Tensor:
        """(H·W, H·W) A, for the coarsest level."""
        h, w = self.diagonal.shape
        n = h * w
        index = torch.arange(n, device=self.diagonal.device).reshape(h, w)
        matrix = torch.diag(self.diag().reshape(-1))
        for weight, a, b in ((self.wx, index[:, :-1], index[:, 1:]), (self.wy, index[:-1], index[1:])):
            matrix[a.reshape(-1), b.reshape(-1)] -= weight.reshape(-1)
            matrix[b.reshape(-1), a.reshape(-1)] -= weight.reshape(-1)
        return matrix


def _pad(values: Tensor, height: int, width: int) -> Tensor:
    return torch.nn.functional.pad(values, (0, width - values.shape[1], 0, height - values.shape[0]))


def _pool(values: Tensor, hc: int, wc: int) -> Tensor:
    """Sums over 2×2 cells (H, W) → (hc, wc), zero-padded."""
    padded = _pad(values, 2 * hc, 2 * wc)
    return padded[0::2, 0::2] + padded[0::2, 1::2] + padded[1::2, 0::2] + padded[1::2, 1::2]


def _prolong(coarse: Tensor, h: int, w: int) -> Tensor:
    return coarse.repeat_interleave(2, dim=0).repeat_interleave(2, dim=1)[:h, :w]


class VCycle:
    """The multigrid hierarchy of a ``GridOperator`` and its symmetric V-cycle (module docstring)."""

    def __init__(self, operator: GridOperator) -> None:
        self.levels = [operator]
        while max(self.levels[-1].diagonal.shape) > COARSEST:
            self.levels.append(self.levels[-1].coarse())
        self.inverse_diag = [DAMPING / level.diag() for level in self.levels]
        self.coarsest = torch.cholesky_inverse(torch.linalg.cholesky(self.levels[-1].dense()))

    def __call__(self, residual: Tensor, depth: int = 0) -> Tensor:
        level = self.levels[depth]
        if depth == len(self.levels) - 1:
            return (self.coarsest @ residual.reshape(-1)).reshape(residual.shape)
        smooth = self.inverse_diag[depth]
        x = smooth * residual
        for _ in range(SWEEPS - 1):
            x = x + smooth * (residual - level.apply(x))
        h, w = residual.shape
        coarse_shape = self.levels[depth + 1].diagonal.shape
        left = _pool(residual - level.apply(x), *coarse_shape)
        x = x + COARSE_SCALE * _prolong(self(left, depth + 1), h, w)
        for _ in range(SWEEPS):
            x = x + smooth * (residual - level.apply(x))
        return x


def solve_grid(operator: GridOperator, rhs: Tensor, tol: float = MULTIGRID_TOL) -> tuple[Tensor, int]:
    """x (H, W) with ``operator``·x = ``rhs`` by multigrid-preconditioned conjugate gradients to a
    relative residual ``tol``, and the iterations taken. RuntimeError when it does not converge in
    MAX_ITERATIONS (an operator that is not positive definite)."""
    cycle = _replayed(VCycle(operator), rhs) if rhs.device.type == "cuda" else VCycle(operator)
    x = torch.zeros_like(rhs)
    r = rhs.clone()
    bound = tol * max(float(torch.linalg.vector_norm(rhs)), 1e-300)
    z = cycle(r)
    p = z.clone()
    rz = torch.sum(r * z)
    for iteration in range(1, MAX_ITERATIONS + 1):
        ap = operator.apply(p)
        alpha = rz / torch.sum(p * ap)
        x += alpha * p
        r -= alpha * ap
        # one read of the device per iteration
        if float(torch.linalg.vector_norm(r)) <= bound:
            return x, iteration
        z = cycle(r)
        rz_next = torch.sum(r * z)
        p = z + (rz_next / rz) * p
        rz = rz_next
    raise RuntimeError(f"multigrid conjugate gradients did not reach {tol:g} in {MAX_ITERATIONS} iterations")


def _replayed(cycle: VCycle, like: Tensor) -> Callable[[Tensor], Tensor]:
    """``cycle`` captured as a CUDA graph on the device of ``like`` (a residual's shape and dtype): each
    call copies its residual into the graph's input and replays it, its answer the graph's own output,
    which the next call overwrites. ``cycle`` itself where CUDA refuses the capture."""
    static = like.clone()
    device = like.device
    # a capture wants the kernels' libraries and the allocator warmed, on a side stream
    side = torch.cuda.Stream(device)
    side.wait_stream(torch.cuda.current_stream(device))
    with torch.cuda.stream(side):
        cycle(static)
    torch.cuda.current_stream(device).wait_stream(side)
    graph = torch.cuda.CUDAGraph()
    try:
        with devices.collector_off(), torch.cuda.graph(graph):
            out = cycle(static)
    except RuntimeError:
        return cycle

    def replay(residual: Tensor) -> Tensor:
        static.copy_(residual)
        graph.replay()
        return out

    return replay


def integrate_normals_on(normal: np.ndarray, mask: np.ndarray, device: str | torch.device) -> np.ndarray:
    """``integrate.integrate_normals`` solved on the torch ``device`` (module docstring): (H, W) float64
    height towards the camera in pixels, 0 outside ``mask`` (H, W) bool, from unit normals (H, W, 3).
    Raises ValueError on mismatched shapes."""
    mask = np.asarray(mask, dtype=bool)
    if normal.shape != (*mask.shape, 3):
        raise ValueError(f"normal {normal.shape} and mask {mask.shape} disagree")
    if not mask.any():
        return np.zeros(mask.shape)
    du, dv, weight = (torch.as_tensor(np.ascontiguousarray(a), dtype=torch.float64, device=device)
                      for a in surface_gradients(np.asarray(normal, dtype=np.float64)))
    inside = torch.as_tensor(mask, device=device)
    # each pair's equation: the mean of its pixels' gradients, weighted by the square of their mean weight
    both_x, both_y = inside[:, 1:] & inside[:, :-1], inside[1:] & inside[:-1]
    wx = torch.where(both_x, (0.5 * (weight[:, 1:] + weight[:, :-1])) ** 2, 0.0)
    wy = torch.where(both_y, (0.5 * (weight[1:] + weight[:-1])) ** 2, 0.0)
    pulled_x = wx * 0.5 * (du[:, 1:] + du[:, :-1])
    pulled_y = wy * 0.5 * (dv[1:] + dv[:-1])
    rhs = torch.zeros_like(du)
    rhs[:, 1:] += pulled_x
    rhs[:, :-1] -= pulled_x
    rhs[1:] += pulled_y
    rhs[:-1] -= pulled_y
    height, _ = solve_grid(GridOperator(wx, wy, torch.full_like(du, SCREEN)), rhs)
    return torch.where(inside, height, 0.0).cpu().numpy()
