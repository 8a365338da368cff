"""``bini``: discontinuity-preserving normal integration in the spirit of Bilateral Normal Integration
(Cao, Santo, Shi, Okura, Matsushita, ECCV 2022), orthographic or perspective.

What is implemented. The unknown x is the height (orthographic, pixels) or the log-depth ũ
(perspective), with the slopes g and equation weights c of ``pstoolkit.surface.perspective.slopes``
(c: the clamped cosine to the line of sight, as in ``poisson``). Every pixel i of the mask gives one
equation per one-sided difference it has inside the mask, using its own slope:

    forward:   x(i+1) − x(i) = g(i)    with weight c(i)²·w⁺(i)
    backward:  x(i) − x(i−1) = g(i)    with weight c(i)²·w⁻(i),  w⁻ = 1 − w⁺

along u and along v (i ± 1: the neighbour along that axis). Iteratively reweighted least squares
alternates a solve of the weighted system with the update

    w⁺(i) = σ(k·c(i)²·((z(i) − z(i−1))² − (z(i+1) − z(i))²)),   σ(t) = 1/(1 + e^−t),

z the surface's depth in ``Surface.depth`` units (pixels orthographic; perspective, the depth scaled
as ``pstoolkit.surface.perspective.depth_of`` scales it, a unit being a pixel across at the median
depth, so ``k`` means the same in both projections), a missing neighbour counting as a zero
difference. A pixel whose one side jumps more than the other trusts its normal on the smooth side
only, so the two sides of a step stop pulling together and the step's height comes from the rest of
the surface. The c² factor (the paper's difference operators carry n_z) keeps a smooth steep slope
from looking like a step: there c·Δz ≈ the normal's sideways component, at most 1. The weights
start at ½; the loop stops when the energy (the weighted sum of squared residuals, with the new
weights) changes by less than ``tolerance`` relatively, or after ``iterations`` solves.

Where it departs from the paper's code. c is n_z clamped to ``MIN_NZ`` (the paper's is unclamped).
For a perspective surface the paper's code weighs ñ_z-scaled log-depth differences, ≈ f·q·Δũ with
q = −n·r; ours, c·Δz ≈ (q/|r|)·(d/f)·f·Δũ, differ by 1/|r| (1 at the image centre) at the median
depth. The free offset is fixed by ``poisson``'s weak pull, here towards the previous iterate (0 at
first) so that it never bends a part the weights leave loosely held. Each weighted system is solved
by conjugate gradients, warm-started at the previous solution and preconditioned with the exact
factorisation of a recent system (refactorised when it stops helping).

Known behaviour: near a smooth but steep rim (a sphere's outline, n_z → 0) the slope changes fast
from pixel to pixel, the weights saturate and each pair takes one pixel's slope rather than the mean
of two, so the last few rings come out slightly too far: sphere depth error after alignment 0.46 %
of the diameter at 128 px and 0.07 % at 256 px, against ``poisson``'s 0.22 % and 0.05 %
(``benchmarks/integrate.py``).
"""

from __future__ import annotations

import time
from typing import Any, ClassVar

import numpy as np
import scipy.sparse.linalg as spla
from scipy.special import expit

from pstoolkit.plugin.options import Option
from pstoolkit.surface.base import Camera, Integrator, Surface, checked_inputs
from pstoolkit.surface.integrate import SCREEN, Pairs, difference_matrix, factorise, neighbour_pairs, normal_matrix
from pstoolkit.surface.perspective import depth_of, slopes

# Conjugate-gradient iterations after which the preconditioner's factorisation is renewed: a recent
# factorisation solves the next system in a few iterations; one this slow means the weights moved.
REFACTOR_AFTER = 25
# Relative residual of each conjugate-gradient solve: far below the IRLS tolerance's effect on depth.
CG_TOLERANCE = 1e-8


class WeightedSolver:
    """Solves (Dᵀ·diag(a)·D + SCREEN·I)·x = rhs + SCREEN·x₀ for changing edge weights ``a`` over
    fixed ``pairs`` (D: ``difference_matrix``), x₀ the previous solution (0 at first): the weak pull
    that fixes each part's offset pulls towards the last iterate, so it fixes the offsets without
    bending a part the weights have left loosely held (``solve_pairs``'s ``refine``). Each solve is
    warm-started at x₀."""

    def __init__(self, pairs: Pairs) -> None:
        self.pairs = pairs
        self.dt = difference_matrix(pairs).T.tocsr()
        self.factor: Any = None
        self.x = np.zeros(pairs.n)
        self.factorisations = 0

    def solve(self, a: np.ndarray, rhs: np.ndarray) -> np.ndarray:
        matrix = normal_matrix(self.pairs, a).tocsr()
        rhs = rhs + SCREEN * self.x
        if self.factor is not None:
            iterations = [0]

            def count(_: np.ndarray) -> None:
                iterations[0] += 1

            preconditioner = spla.LinearOperator(matrix.shape, self.factor.solve)
            x, info = spla.cg(matrix, rhs, x0=self.x, M=preconditioner, rtol=CG_TOLERANCE, maxiter=REFACTOR_AFTER, callback=count)
            if info == 0:
                self.x = x
                if iterations[0] >= REFACTOR_AFTER // 2:
                    self.factor = None  # converging slowly: the next solve refactorises
                return x
        self.factor = factorise(matrix)
        self.factorisations += 1
        self.x = self.factor.solve(rhs)
        return self.x


def bilateral_weights(depth: np.ndarray, c: np.ndarray, pairs: Pairs, k: float) -> np.ndarray:
    """(n, 2) w⁺ of each unknown along u (column 0) and v (column 1) from its ``depth`` (n,) and
    equation weight ``c`` (n,): the sigmoid of the module docstring, a missing neighbour counting as
    a zero difference."""
    forward, backward = np.zeros((pairs.n, 2)), np.zeros((pairs.n, 2))
    column = np.where(pairs.axis == 1, 0, 1)
    step = depth[pairs.second] - depth[pairs.first]
    forward[pairs.first, column] = step
    backward[pairs.second, column] = step
    return expit(k * c[:, None] ** 2 * (backward**2 - forward**2))


class BiNIIntegrator(Integrator):
    name: ClassVar[str] = "bini"
    summary: ClassVar[str] = "bilateral normal integration (Cao et al. 2022): IRLS that keeps depth steps, orthographic or perspective"
    options: ClassVar[tuple[Option, ...]] = (
        Option("k", float, 2.0, "sharpness of the sigmoid weighing the one-sided depth differences (per squared unit of depth)",
               minimum=0.0, maximum=1e6),
        Option("iterations", int, 100, "most reweighted solves", minimum=1, maximum=10000),
        Option("tolerance", float, 1e-4, "stop when the energy changes by less than this share", minimum=0.0, maximum=1.0),
    )

    def integrate(self, normal: np.ndarray, mask: np.ndarray, options: dict[str, Any], camera: Camera | None = None) -> Surface:
        start = time.perf_counter()
        normal, mask = checked_inputs(normal, mask)
        pairs = neighbour_pairs(mask)
        du, dv, c = slopes(normal, camera)
        # per pair: the slope of its first pixel (forward equation) and second (backward), and weights
        horizontal = pairs.axis == 1
        g_first = np.where(horizontal, du.ravel()[pairs.lo], dv.ravel()[pairs.lo])
        g_second = np.where(horizontal, du.ravel()[pairs.hi], dv.ravel()[pairs.hi])
        c2_first, c2_second = c.ravel()[pairs.lo] ** 2, c.ravel()[pairs.hi] ** 2
        column = np.where(horizontal, 0, 1)
        solver = WeightedSolver(pairs)
        w = np.full((pairs.n, 2), 0.5)  # the paper's start: both sides of every pixel trusted alike
        energy, solves, converged = np.inf, 0, False
        x = np.zeros(pairs.n)
        while solves < options["iterations"] and not converged:
            solves += 1
            alpha = c2_first * w[pairs.first, column]  # forward equation of the first pixel
            beta = c2_second * (1.0 - w[pairs.second, column])  # backward equation of the second
            x = solver.solve(alpha + beta, solver.dt @ (alpha * g_first + beta * g_second))
            z = depth_of(_scatter(x, mask), mask, camera)[mask]
            w = bilateral_weights(z, c[mask], pairs, options["k"])
            step = x[pairs.second] - x[pairs.first]
            alpha = c2_first * w[pairs.first, column]
            beta = c2_second * (1.0 - w[pairs.second, column])
            previous, energy = energy, float(np.sum(alpha * (step - g_first) ** 2 + beta * (step - g_second) ** 2))
            converged = bool(np.isfinite(previous) and abs(energy - previous) <= options["tolerance"] * previous)
        depth = depth_of(_scatter(x, mask), mask, camera)
        diagnostics = {"iterations": solves, "converged": converged, "energy": energy, "factorisations": solver.factorisations}
        return Surface(depth, mask, "orthographic" if camera is None else "perspective", time.perf_counter() - start, diagnostics)


def _scatter(values: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(H, W) with ``values`` (n,) at the mask's pixels in row-major order, 0 elsewhere."""
    out = np.zeros(mask.shape)
    out[mask] = values
    return out
