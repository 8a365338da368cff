"""Orthographic normal integration: the height map whose gradients best match a normal map.

With x right, y up, z towards the camera and image row v growing downwards, a surface of height h(u, v)
towards the camera (in pixels) has the normal ∝ (−∂h/∂u, ∂h/∂v, 1), so ∂h/∂u = −n_x/n_z and
∂h/∂v = n_y/n_z. ``integrate_normals`` solves the least-squares (screened Poisson) problem over
the mask: one equation h(u+1, v) − h(u, v) = ½(p(u, v) + p(u+1, v)) per pair of horizontal
neighbours inside the mask, likewise vertically, each weighted by the pair's mean n_z (a grazing
normal's slope is the least certain), plus a weak pull of every height towards zero that fixes the
free offset of each connected part. A depth step the normals cannot see (an occluding contour) comes
out as the steepest slope the clamped gradients allow, spread over the pixels beside it.

The solve itself (``integrate_gradients``) takes any gradient field with its weights, so the
perspective integrators (``pstoolkit.surface.perspective``: gradients of log-depth) and the
discontinuity-preserving one (``pstoolkit.surface.bini``: the same pairs, reweighted) share it.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

# Smallest n_z used for a slope: at most 1/MIN_NZ pixels of height per pixel.
MIN_NZ = 0.05
# Weight of the pull towards height 0 against a unit-weight gradient equation: fixes each connected
# part's offset without bending it.
SCREEN = 1e-6
# Above this many unknowns the solve is algebraic multigrid instead of a sparse LU, whose fill (and
# time) grows faster than the unknowns: 1.2 GB of factors at a full 1024² frame, 8 s against 6.5 s.
DIRECT_MAX_UNKNOWNS = 300_000
# Relative residual of the multigrid solve: heights within 1e-9 px of the LU's at 1024².
MULTIGRID_TOL = 1e-10


class Pairs(NamedTuple):
    """The neighbour pairs inside a mask of n pixels: ``index`` (H, W) int64, each mask pixel's
    unknown (−1 outside); ``first``/``second`` (M,) the unknowns of each pair, ``second`` the right
    (axis 1) or lower (axis 0) neighbour; ``lo``/``hi`` (M,) the flat pixel indices (v·W + u) of
    the same; ``axis`` (M,) 1 for horizontal pairs, then 0 for vertical ones."""

    index: np.ndarray
    n: int
    first: np.ndarray
    second: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    axis: np.ndarray


def neighbour_pairs(mask: np.ndarray) -> Pairs:
    """Every pair of 4-neighbours both inside ``mask`` (H, W) bool: horizontal pairs first, then
    vertical, each in row-major order of their first pixel."""
    height, width = mask.shape
    n = int(mask.sum())
    index = np.full((height, width), -1, dtype=np.int64)
    index[mask] = np.arange(n)
    flat = np.arange(height * width).reshape(height, width)
    firsts, seconds, los, his, axes = [], [], [], [], []
    for axis in (1, 0):
        lo = (slice(None), slice(None, -1)) if axis == 1 else (slice(None, -1), slice(None))
        hi = (slice(None), slice(1, None)) if axis == 1 else (slice(1, None), slice(None))
        both = mask[lo] & mask[hi]
        firsts.append(index[lo][both])
        seconds.append(index[hi][both])
        los.append(flat[lo][both])
        his.append(flat[hi][both])
        axes.append(np.full(int(both.sum()), axis, dtype=np.int8))
    return Pairs(index, n, *(np.concatenate(parts) for parts in (firsts, seconds, los, his, axes)))


def difference_matrix(pairs: Pairs) -> sp.csr_matrix:
    """(M, n) sparse: row k gives value[second_k] − value[first_k]."""
    m = pairs.first.size
    rows = np.concatenate([np.arange(m), np.arange(m)])
    values = np.concatenate([np.ones(m), -np.ones(m)])
    return sp.csr_matrix((values, (rows, np.concatenate([pairs.second, pairs.first]))), shape=(m, pairs.n))


def solve_pairs(pairs: Pairs, weight: np.ndarray, target: np.ndarray, refine: int = 0,
                direct_max: int = DIRECT_MAX_UNKNOWNS) -> np.ndarray:
    """(n,) values minimising Σ_k weight_k·(value[second_k] − value[first_k] − target_k)² +
    SCREEN·Σ value² over the unknowns of ``pairs``; ``weight`` and ``target`` (M,). The screen term
    keeps the system positive definite and sets each connected part's mean near 0.

    Its pull also bends what is loosely held (a long thin part far from 0), so each of ``refine``
    further solves pulls towards the previous solution instead of 0 (a proximal step on the same
    factorisation, about 1/30 of its cost): the offsets stay, the bend shrinks by SCREEN over the
    part's stiffness each time. Up to ``direct_max`` unknowns the solve is a sparse LU, above it
    smoothed-aggregation multigrid with conjugate gradients (``solve_multigrid``)."""
    # summed into CSR at once: the unsummed COO is four times its size
    matrix = normal_matrix(pairs, weight).tocsr()
    # Dᵀ(w·t) from the pairs, like the matrix
    pulled = weight * target
    rhs = np.bincount(pairs.second, weights=pulled, minlength=pairs.n) - np.bincount(pairs.first, weights=pulled, minlength=pairs.n)
    if pairs.n > direct_max:
        return solve_multigrid(matrix, rhs, refine)
    # a sparse direct solve: about 0.2 s for a 256² map on this machine, faster than CG on the Laplacian
    return solve_pairs_direct(matrix, rhs, refine)


def normal_matrix(pairs: Pairs, weight: np.ndarray) -> sp.coo_matrix:
    """(n, n) Dᵀ·diag(``weight``)·D + SCREEN·I of ``pairs`` (D: ``difference_matrix``, ``weight`` (M,)),
    assembled from the pairs: the sparse products built copies of D and of their result, half the
    solve's peak memory at a full 1024² frame. Unsummed COO: convert it to the format the solver wants."""
    first, second, diagonal = pairs.first, pairs.second, np.arange(pairs.n)
    return sp.coo_matrix(
        (np.concatenate([weight, weight, -weight, -weight, np.full(pairs.n, SCREEN)]),
         (np.concatenate([first, second, first, second, diagonal]), np.concatenate([first, second, second, first, diagonal]))),
        shape=(pairs.n, pairs.n))


def factorise(matrix: sp.spmatrix) -> Any:
    """The sparse LU (``scipy.sparse.linalg.SuperLU``) of a symmetric ``normal_matrix``. A minimum-degree
    ordering of A + Aᵀ with diagonal pivots fills in far less than the default column ordering
    (measured in docs/dualres-tuning.md, "Speed")."""
    return spla.splu(matrix.tocsc(), permc_spec="MMD_AT_PLUS_A", options={"SymmetricMode": True})


def solve_multigrid(matrix: sp.spmatrix, rhs: np.ndarray, refine: int = 0) -> np.ndarray:
    """``solve_pairs``'s system ``matrix``·x = ``rhs`` (symmetric positive definite) by pyamg's
    smoothed aggregation as the preconditioner of conjugate gradients, to MULTIGRID_TOL; the
    ``refine`` proximal solves reuse the hierarchy, each started from the previous solution. Memory
    grows with the unknowns, not with an LU's fill; a solve that misses the tolerance falls back to
    the LU."""
    import pyamg

    matrix = matrix.tocsr()
    hierarchy = pyamg.smoothed_aggregation_solver(matrix, symmetry="symmetric")
    values = None
    for step in range(refine + 1):
        b = rhs if step == 0 else rhs + SCREEN * values
        values = hierarchy.solve(b, x0=values, tol=MULTIGRID_TOL, accel="cg", maxiter=200)
        if np.linalg.norm(matrix @ values - b) > 100 * MULTIGRID_TOL * max(np.linalg.norm(b), 1e-300):
            return solve_pairs_direct(matrix, rhs, refine)
    return np.asarray(values, dtype=np.float64)


def solve_pairs_direct(matrix: sp.spmatrix, rhs: np.ndarray, refine: int = 0) -> np.ndarray:
    """``solve_pairs``'s system by a sparse LU (``factorise``), with the ``refine`` proximal solves on
    its factors."""
    factor = factorise(matrix)
    values = factor.solve(rhs)
    for _ in range(refine):
        values = factor.solve(rhs + SCREEN * values)
    return np.asarray(values, dtype=np.float64)


def surface_gradients(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(∂h/∂u, ∂h/∂v, weight) (H, W) each, from unit normals (H, W, 3); n_z is clamped to ``MIN_NZ``
    and the weight is the clamped n_z."""
    nz = np.maximum(np.asarray(normal[..., 2], dtype=np.float64), MIN_NZ)
    return -normal[..., 0] / nz, normal[..., 1] / nz, nz


def integrate_gradients(du: np.ndarray, dv: np.ndarray, weight: np.ndarray, mask: np.ndarray, refine: int = 0) -> np.ndarray:
    """(H, W) float64 values whose differences best match the gradients ``du`` = ∂/∂u, ``dv`` = ∂/∂v
    (H, W) over ``mask`` (H, W) bool, 0 outside: each pair of neighbours gets the mean of its two
    pixels' gradient and, squared, the mean of their ``weight`` as its equation's weight (see the
    module docstring); ``refine`` as in ``solve_pairs``."""
    mask = np.asarray(mask, dtype=bool)
    out = np.zeros(mask.shape)
    pairs = neighbour_pairs(mask)
    if pairs.n == 0:
        return out
    horizontal = pairs.axis == 1
    grad = np.where(horizontal, du.ravel()[pairs.lo] + du.ravel()[pairs.hi], dv.ravel()[pairs.lo] + dv.ravel()[pairs.hi])
    w = 0.5 * (weight.ravel()[pairs.lo] + weight.ravel()[pairs.hi])
    out[mask] = solve_pairs(pairs, w**2, 0.5 * grad, refine)
    return out


def integrate_normals(normal: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(H, W) float64 height towards the camera in pixels, 0 outside ``mask`` (H, W) bool, from unit
    normals (H, W, 3) in the camera frame; each connected part of the mask has mean height near 0.
    Raises ValueError on mismatched shapes."""
    mask = np.asarray(mask, dtype=bool)
    if normal.shape != (*mask.shape, 3):
        raise ValueError(f"normal {normal.shape} and mask {mask.shape} disagree")
    return integrate_gradients(*surface_gradients(np.asarray(normal, dtype=np.float64)), mask)
