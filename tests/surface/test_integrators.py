"""The registered integrators: analytic spheres come back within a fraction of their size, orthographic
and through a camera; ``bini`` keeps a step that ``poisson`` spreads; the registry holds both and
refuses other kinds; bad input is refused with a clear message."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from pstoolkit.evaluation.metrics import depth_error
from pstoolkit.plugin.manager import get_registries
from pstoolkit.plugin.registry import PluginError, Registries
from pstoolkit.surface import Camera, Integrator, Surface, points
from pstoolkit.surface.bini import BiNIIntegrator
from pstoolkit.surface.poisson import PoissonIntegrator
from pstoolkit.surface.shapes import perspective_sphere, sphere, step_jump, two_planes

INTEGRATORS = [PoissonIntegrator, BiNIIntegrator]


def defaults(integrator: type[Integrator]) -> dict[str, Any]:
    return {o.name: o.default for o in integrator.options}


def test_the_registry_lists_poisson_and_bini(pstoolkit_plugins: pytest.MonkeyPatch) -> None:
    integrators = get_registries().integrators
    assert {"poisson", "bini"} <= set(integrators.names())
    assert integrators.get("poisson").obj is PoissonIntegrator and integrators.get("bini").obj is BiNIIntegrator
    assert {integrators.get(n).plugin for n in ("poisson", "bini")} == {"core"}
    assert integrators.get("bini").parse_options(["k=4"]) == {"k": 4.0, "iterations": 100, "tolerance": 1e-4}


def test_a_registration_of_another_kind_is_refused() -> None:
    from pstoolkit.solve.base import Solver

    class Mistaken(Solver):
        name = "mistaken"
        summary = "a solver offered as an integrator"

    registries = Registries()
    with registries.integrators.registering_for("p"), pytest.raises(PluginError) as info:
        registries.integrators.register(Mistaken)
    assert str(info.value) == (
        f"plugin 'p': integrator 'mistaken' is {__name__}.{Mistaken.__qualname__}, not a subclass of pstoolkit.surface.base.Integrator"
    )
    assert registries.integrators.names() == []


@pytest.mark.parametrize("integrator", INTEGRATORS, ids=lambda i: i.name)
@pytest.mark.parametrize("size", [96, 128])
def test_an_orthographic_sphere_comes_back_within_half_a_percent_of_its_diameter(integrator: type[Integrator], size: int) -> None:
    truth = sphere(size, 0.45 * size)
    surface = integrator().integrate(truth.normal, truth.mask, defaults(integrator))
    error = depth_error(surface.depth, truth.depth, truth.mask)
    # measured: poisson 0.29 % / 0.22 %, bini 0.21 % / 0.46 % (its rim, see pstoolkit.surface.bini)
    assert error.rmse < 0.005 * 0.9 * size
    assert abs(error.scale - 1.0) < 0.02  # frame pixels, like the truth
    assert surface.projection == "orthographic" and np.array_equal(surface.mask, truth.mask)
    assert np.isnan(surface.depth[~truth.mask]).all() and np.isfinite(surface.depth[truth.mask]).all()
    assert surface.seconds > 0


@pytest.mark.parametrize("integrator", INTEGRATORS, ids=lambda i: i.name)
def test_a_sphere_seen_through_a_camera_comes_back_up_to_scale(integrator: type[Integrator]) -> None:
    # a unit sphere 3 units in front of a 96 px camera with a 51° field of view, about 70 px across
    truth = perspective_sphere(96, focal=100.0, distance=3.0, radius=1.0)
    assert truth.camera is not None
    surface = integrator().integrate(truth.normal, truth.mask, defaults(integrator), camera=truth.camera)
    assert surface.projection == "perspective"
    error = depth_error(surface.depth, truth.depth, truth.mask)
    assert error.rmse < 0.005 * 2.0  # within 0.5 % of the diameter; measured poisson 0.24 %, bini 0.17 %
    # the scale the integrators choose: the median distance along the axis is the focal length
    assert np.median(-surface.depth[truth.mask]) == pytest.approx(100.0)
    # with that scale undone, the points lie on the sphere (the offset of a perspective depth is 0)
    scale = float(np.median(truth.depth[truth.mask] / surface.depth[truth.mask]))
    placed = points(surface, truth.camera)[truth.mask] * scale
    radius = np.linalg.norm(placed - np.array([0.0, 0.0, -3.0]), axis=-1)
    assert np.sqrt(np.mean((radius - 1.0) ** 2)) < 0.005


def test_a_long_focal_length_gives_the_orthographic_shape() -> None:
    truth = sphere(64, 24.0)
    far = Camera(fx=1e6, fy=1e6, cx=31.5, cy=31.5)
    ortho = PoissonIntegrator().integrate(truth.normal, truth.mask, {})
    persp = PoissonIntegrator().integrate(truth.normal, truth.mask, {}, camera=far)
    # z = −d with d ≈ 1e6 ± the relief: the same relief once aligned, to well under a pixel
    assert depth_error(persp.depth, ortho.depth, truth.mask).rmse < 1e-3


@pytest.mark.parametrize("integrator", INTEGRATORS, ids=lambda i: i.name)
def test_bini_keeps_a_step_that_poisson_spreads(integrator: type[Integrator]) -> None:
    size, jump = 64, 16.0
    truth = two_planes(size, jump, lip=4.0)
    assert step_jump(truth.depth, size) == jump
    surface = integrator().integrate(truth.normal, truth.mask, defaults(integrator))
    measured = step_jump(surface.depth, size)
    if integrator is BiNIIntegrator:
        assert abs(measured - jump) < 0.1 * jump  # measured 1.000·jump
        assert surface.diagnostics["converged"]
    else:
        assert measured < 0.5 * jump  # measured 0.23·jump: least squares spreads the step over the planes and the ramp


@pytest.mark.parametrize("integrator", INTEGRATORS, ids=lambda i: i.name)
def test_bad_input_is_refused_with_a_clear_message(integrator: type[Integrator]) -> None:
    run = integrator().integrate
    options = defaults(integrator)
    with pytest.raises(ValueError, match=r"^normal map of shape \(4, 4, 3\) does not fit mask of shape \(5, 4\) \(expected \(5, 4, 3\)\)$"):
        run(np.zeros((4, 4, 3)), np.ones((5, 4), dtype=bool), options)
    with pytest.raises(ValueError, match=r"^mask must be \(H, W\), got shape \(4, 4, 1\)$"):
        run(np.zeros((4, 4, 3)), np.ones((4, 4, 1), dtype=bool), options)
    normal = np.zeros((4, 4, 3))
    normal[..., 2] = 1.0
    normal[1, 2] = 0.0
    normal[2, 2, 0] = np.nan
    with pytest.raises(ValueError, match=r"^2 pixels of the mask have a zero or non-finite normal; leave them out of the mask$"):
        run(normal, np.ones((4, 4), dtype=bool), options)
    mask = np.ones((4, 4), dtype=bool)
    mask[1, 2] = mask[2, 2] = False  # left out, those pixels are fine
    assert np.isnan(run(normal, mask, options).depth[~mask]).all()


def test_an_empty_mask_gives_an_empty_surface() -> None:
    for integrator in INTEGRATORS:
        surface = integrator().integrate(np.zeros((3, 5, 3)), np.zeros((3, 5), dtype=bool), defaults(integrator))
        assert surface.depth.shape == (3, 5) and np.isnan(surface.depth).all() and not surface.mask.any()


def test_orthographic_points_are_centred_pixels() -> None:
    depth = np.arange(6, dtype=np.float64).reshape(2, 3)
    mask = np.array([[True, True, False], [True, True, True]])
    xyz = points(Surface(depth, mask, "orthographic", 0.0))
    np.testing.assert_array_equal(xyz[0, 0], [-1.0, 0.5, 0.0])  # u − (W−1)/2, (H−1)/2 − v, z
    np.testing.assert_array_equal(xyz[1, 2], [1.0, -0.5, 5.0])
    assert np.isnan(xyz[0, 2]).all()


def test_perspective_points_lie_on_the_pixel_rays() -> None:
    camera = Camera(fx=50.0, fy=40.0, cx=1.0, cy=0.5)
    surface = Surface(np.full((2, 3), -10.0), np.ones((2, 3), dtype=bool), "perspective", 0.0)
    xyz = points(surface, camera)
    np.testing.assert_allclose(xyz[0, 2], [(2 - 1.0) / 50.0 * 10.0, -(0 - 0.5) / 40.0 * 10.0, -10.0])
    with pytest.raises(ValueError, match="needs its camera"):
        points(surface)


def test_cameras_are_checked_and_read_from_a_matrix() -> None:
    assert Camera.from_matrix(np.array([[500.0, 0.0, 320.0], [0.0, 510.0, 240.0], [0.0, 0.0, 1.0]])) == Camera(500.0, 510.0, 320.0, 240.0)
    with pytest.raises(ValueError, match="focal lengths must be positive"):
        Camera(fx=0.0, fy=1.0, cx=0.0, cy=0.0)
    with pytest.raises(ValueError, match="must be finite"):
        Camera(fx=1.0, fy=1.0, cx=float("nan"), cy=0.0)
    with pytest.raises(ValueError, match="3×3"):
        Camera.from_matrix(np.eye(4))
