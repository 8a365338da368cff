"""Normal integration: analytic surfaces come back within a fraction of a pixel, each connected part
of the mask is centred, and bad shapes are refused."""

from __future__ import annotations

import numpy as np
import pytest

from pstoolkit.surface import integrate_normals, surface_gradients
from pstoolkit.surface.integrate import neighbour_pairs, solve_pairs


def _sphere(size: int, radius: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    v, u = np.mgrid[0:size, 0:size] + 0.5
    x, y = u - size / 2, -(v - size / 2)
    mask = x**2 + y**2 < radius**2
    z = np.sqrt(np.clip(radius**2 - x**2 - y**2, 0.0, None))
    return np.stack([x, y, z], axis=-1) / radius, z, mask


def test_a_sphere_comes_back_within_half_a_percent_of_its_diameter() -> None:
    normal, z, mask = _sphere(96, 40.0)
    height = integrate_normals(normal, mask)
    error = (height - z)[mask]
    error -= error.mean()
    assert np.sqrt(np.mean(error**2)) < 0.005 * 80.0  # measured 0.24 px
    assert np.all(height[~mask] == 0.0)


def test_a_tilted_plane_comes_back_and_parts_are_centred() -> None:
    size = 40
    v, u = np.mgrid[0:size, 0:size].astype(np.float64)
    slope_u, slope_v = 0.3, -0.2  # ∂h/∂u and ∂h/∂v in pixels per pixel
    normal = np.stack([np.full_like(u, -slope_u), np.full_like(u, slope_v), np.ones_like(u)], axis=-1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    mask = np.zeros((size, size), dtype=bool)
    mask[2:18, 2:38] = True
    mask[24:38, 5:30] = True  # a second, disconnected part
    height = integrate_normals(normal, mask)
    for part in (np.s_[2:18, 2:38], np.s_[24:38, 5:30]):
        h = height[part]
        np.testing.assert_allclose(np.diff(h, axis=1), slope_u, atol=1e-3)  # the weak pull to 0 bends by 5e-5
        np.testing.assert_allclose(np.diff(h, axis=0), slope_v, atol=1e-3)
        assert abs(h.mean()) < 1e-3


def test_gradients_follow_the_camera_frame_and_clamp_grazing_normals() -> None:
    du, dv, weight = surface_gradients(np.array([[[0.6, 0.0, 0.8], [0.0, 0.6, 0.8], [1.0, 0.0, 0.0]]]))
    np.testing.assert_allclose(du[0, :2], [-0.75, 0.0])  # x right: a normal leaning right means height falls to the right
    np.testing.assert_allclose(dv[0, :2], [0.0, 0.75])  # y up, rows down: leaning up means height grows down the rows
    assert du[0, 2] == -20.0 and weight[0, 2] == 0.05


def test_mismatched_shapes_are_refused() -> None:
    with pytest.raises(ValueError, match=r"normal \(4, 4, 3\) and mask \(5, 4\) disagree"):
        integrate_normals(np.zeros((4, 4, 3)), np.ones((5, 4), dtype=bool))


def test_the_multigrid_solve_is_the_direct_one() -> None:
    """Above ``DIRECT_MAX_UNKNOWNS`` the pairs are solved by smoothed-aggregation multigrid with CG
    instead of a sparse LU: the same heights (to 1e-6 px, on a mask of two parts with weights spread
    over two decades), proximal refinements included."""
    rng = np.random.default_rng(0)
    rows, cols = np.mgrid[:120, :160]
    mask = ((cols - 80) ** 2 / 75**2 + (rows - 60) ** 2 / 55**2) < 1
    mask[:, 100:104] = False
    pairs = neighbour_pairs(mask)
    weight = rng.uniform(0.01, 1.0, pairs.first.size)
    target = rng.normal(size=pairs.first.size)
    for refine in (0, 2):
        direct = solve_pairs(pairs, weight, target, refine)
        multigrid = solve_pairs(pairs, weight, target, refine, direct_max=0)
        assert np.ptp(direct) > 1.0
        np.testing.assert_allclose(multigrid, direct, atol=1e-6)
