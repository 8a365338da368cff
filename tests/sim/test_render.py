"""Rendering: cast shadows against the geometry, frame integrals against closed forms, the event grid."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import distance_transform_edt, map_coordinates

from pstoolkit.grid import area_weights
from pstoolkit.optics.equivalent import equivalent_lights, sample_times
from pstoolkit.optics.lights import NearRingLight, RingLight
from pstoolkit.optics.shadow_sweep import ShadowCaster, cast_shadow_mask
from pstoolkit.plugin.manager import get_registries
from pstoolkit.plugin.options import defaults
from pstoolkit.sim.exposure import exposure_samples, integrate
from pstoolkit.sim.render import Renderer
from pstoolkit.sim.scenes import Blobs, SceneMaps, Sphere

LAMBERTIAN = get_registries().brdfs.get("lambertian").obj
GGX = get_registries().brdfs.get("ggx").obj


def direction(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    a, e = np.radians(azimuth_deg), np.radians(elevation_deg)
    return np.array([[np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)]])


def block_on_plane(size: int = 48, height: float = 8.0) -> tuple[np.ndarray, np.ndarray]:
    """An 8 px tall block over rows 16–31 and columns 16–23: 16 px of plane on every side."""
    depth = np.zeros((size, size))
    depth[16:32, 16:24] = height
    return depth, np.ones((size, size), bool)


@pytest.mark.parametrize("elevation", [30.0, 45.0, 60.0])
@pytest.mark.parametrize("azimuth", [0.0, 90.0, 180.0, 270.0])
def test_shadow_behind_a_step_edge_is_height_over_tan_elevation_long(azimuth: float, elevation: float) -> None:
    depth, mask = block_on_plane()
    shadow = cast_shadow_mask(depth, mask, direction(azimuth, elevation))[0]
    expected = 8.0 / np.tan(np.radians(elevation))
    # the light comes from the +x (0°), +y (90°, image up) … side, so the shadow falls on the other
    behind = {0.0: shadow[16:32, :16], 180.0: shadow[16:32, 24:], 90.0: shadow[32:, 16:24], 270.0: shadow[:16, 16:24]}
    lengths = behind[azimuth].sum(axis=1 if azimuth in (0.0, 180.0) else 0)
    assert np.all(np.abs(lengths - expected) <= 1.0 + 1e-9), (lengths, expected)
    assert shadow.sum() == lengths.sum()  # nothing shadowed beside the block or in front of it
    assert not shadow[depth > 0].any()


def test_shadow_region_matches_the_geometry_within_a_pixel_from_any_side() -> None:
    """Reference: each pixel's own ray marched in 0.05 px steps over the depth map as a bilinear
    surface. A pixel may differ only within one pixel of the reference shadow's edge, or right beside
    the block (a ray grazing a wall is shadowed over part of the pixel's footprint)."""
    depth, mask = block_on_plane()
    v, u = np.mgrid[0:48, 0:48].astype(np.float64)
    steps = np.arange(1, 300) * 0.05
    beside_block = distance_transform_edt(depth == 0) <= 1.0
    for azimuth in range(0, 360, 20):
        for elevation in (30.0, 55.0):
            shadow = cast_shadow_mask(depth, mask, direction(azimuth, elevation))[0]
            du, dv = np.cos(np.radians(azimuth)), -np.sin(np.radians(azimuth))  # unit step in the image
            uu, vv = u[..., None] + steps * du, v[..., None] + steps * dv
            surface = map_coordinates(depth, [vv.ravel(), uu.ravel()], order=1, cval=0.0).reshape(uu.shape)
            reference = np.any(surface > depth[..., None] + steps * np.tan(np.radians(elevation)) + 0.1, axis=-1)
            to_edge = np.where(reference, distance_transform_edt(reference), distance_transform_edt(~reference))
            wrong = (shadow != reference) & ~beside_block
            assert not wrong.any() or to_edge[wrong].max() <= 1.0, (azimuth, elevation)


def test_column_major_margins_are_the_transposed_maps_of_the_lights_along_the_rows() -> None:
    """``margins(column_major=True)`` stores the maps of lights running more along the image rows
    (|l_x| ≥ |l_y|) transposed, the others as they are, equal to the row-major sweep in every
    orientation, on a map that is not square, in margins and in V."""
    depth, mask = block_on_plane(48)
    depth, mask = depth[:, :41], mask[:, :41]
    lights = np.concatenate([direction(a, 35.0) for a in np.arange(0.0, 360.0, 11.0)] + [direction(0.0, 90.0)])
    caster = ShadowCaster(depth, mask)
    major = ShadowCaster.column_major_lights(lights)
    np.testing.assert_array_equal(major[:-1], np.abs(lights[:-1, 0]) >= np.abs(lights[:-1, 1]))
    assert not major[-1]
    for openness in (False, True):
        rows = caster.margins(lights, openness=openness)
        stored = caster.margins(lights, openness=openness, column_major=True)
        assert (rows[:-1].min(axis=(1, 2)) < rows[:-1].max(axis=(1, 2))).all()
        for g in range(len(lights)):
            got = stored[g].reshape(41, 48).T if major[g] else stored[g]
            # bit-equal: column-major storage writes the same sweep's values elsewhere (no fastmath)
            np.testing.assert_array_equal(got, rows[g], err_msg=f"light {g}")


def test_convex_sphere_casts_no_shadow_on_its_lit_side_and_overhead_light_none_at_all() -> None:
    maps = Sphere().build(48, 0, **defaults(Sphere.options))
    light = RingLight(elevation_deg=20.0, period_us=1000.0)
    directions, _ = light.evaluate(sample_times(0, 1000, 36))
    shadow = cast_shadow_mask(maps.depth, maps.mask, directions)
    facing = np.einsum("hwx,tx->thw", maps.normal, directions) > 0
    assert not (shadow & facing).any()
    assert (shadow & ~facing & maps.mask).sum() > 0.5 * (~facing & maps.mask).sum()  # rays into the far side
    depth, mask = block_on_plane()
    assert not cast_shadow_mask(depth, mask, np.array([[0.0, 0.0, 1.0]])).any()


def lambertian_sphere(size: int = 48) -> SceneMaps:
    return Sphere().build(size, 0, **{**defaults(Sphere.options), "albedo": "texture"})


def test_frame_integral_of_lambertian_sphere_equals_the_equivalent_light() -> None:
    """A = ρ ⊙ (L*·n) where the pixel stays lit all window (DualResPS eq. 12), L* in closed form."""
    maps = lambertian_sphere()
    light = RingLight(elevation_deg=40.0, period_us=30000.0, intensity=np.array([1.0, 0.8, 0.6]))
    renderer = Renderer(maps, light, LAMBERTIAN())
    for t0, t1 in ((0, 10000), (10000, 20000), (20000, 30000)):
        (exposure,) = integrate(renderer, t0, t1)
        star = light.intensity[:, None] * light.integral(t0, t1)  # (RGB, xyz), closed form for a ring
        np.testing.assert_allclose(equivalent_lights(light, t0, t1), star, rtol=1e-4, atol=1e-12)
        expected = maps.albedo * np.einsum("cx,hwx->hwc", star, maps.normal)
        directions, _ = light.evaluate(sample_times(t0, t1, 2000))
        always_lit = maps.mask & np.all(np.einsum("tx,hwx->thw", directions, maps.normal) > 0, axis=0)
        assert always_lit.sum() > 0.4 * maps.mask.sum()
        relative = np.abs(exposure[always_lit] - expected[always_lit]) / expected[always_lit]
        assert relative.max() < 0.005


def test_default_sample_count_is_within_half_a_percent_of_a_ten_times_denser_integral() -> None:
    maps = Blobs().build(48, 1, **defaults(Blobs.options))
    light = RingLight(elevation_deg=35.0, period_us=30000.0)
    renderer = Renderer(maps, light, GGX())
    n = exposure_samples(light, 0, 10000)
    # the direction sweeps 120° of azimuth on a cone of elevation 35°: an arc of 120°·cos 35°
    assert n == int(np.ceil(120.0 * np.cos(np.radians(35.0)) / 0.5))
    (coarse,) = integrate(renderer, 0, 10000)
    (dense,) = integrate(renderer, 0, 10000, samples=10 * n)
    assert np.abs(coarse - dense).max() < 0.005 * dense.max()
    shadowed = cast_shadow_mask(maps.depth, maps.mask, light.evaluate(sample_times(0, 10000, 8))[0])
    assert shadowed.any(axis=0).mean() > 0.05  # the scene does have cast shadows to resolve


def test_ggx_adds_a_highlight_and_diffuse_part_is_the_lambertian_render() -> None:
    maps = lambertian_sphere(32)
    light = RingLight(elevation_deg=60.0, period_us=9000.0)
    renderer = Renderer(maps, light, GGX())
    full, diffuse = integrate(renderer, 0, 3000, brdfs=[GGX(), LAMBERTIAN()])
    (lambert,) = integrate(Renderer(maps, light, LAMBERTIAN()), 0, 3000)
    np.testing.assert_allclose(diffuse, lambert, rtol=1e-6, atol=1e-12)
    assert np.all(full >= diffuse - 1e-9)
    assert (full - diffuse).max() > 0.05 * diffuse.max()


def test_event_grey_is_the_area_average_of_the_frame_grey() -> None:
    maps = lambertian_sphere(32)
    renderer = Renderer(maps, RingLight(elevation_deg=45.0, period_us=1000.0), GGX())
    t = np.array([0.0, 250.0, 600.0])
    rgb = renderer.image(t).astype(np.float64)
    grey = rgb @ np.array([0.299, 0.587, 0.114])
    expected = grey.reshape(3, 16, 2, 16, 2).mean(axis=(2, 4))
    np.testing.assert_allclose(renderer.event_grey(t, 0.5), expected, rtol=1e-5, atol=1e-7)


def test_area_weights_cover_each_event_pixel_exactly_once() -> None:
    w = area_weights(12, 30, 0.4)  # 2.5 frame pixels per event pixel
    np.testing.assert_allclose(w.sum(axis=1), 1.0)
    np.testing.assert_allclose(w.sum(axis=0), 0.4)
    np.testing.assert_allclose(w[0, :3], [0.4, 0.4, 0.2])


def test_a_far_near_light_renders_like_the_directional_ring() -> None:
    maps = lambertian_sphere(32)
    far = 1e7
    elevation = 45.0
    near = NearRingLight(radius_mm=far, height_mm=far, pixel_pitch_mm=0.1, period_us=1000.0)
    ring = RingLight(elevation_deg=elevation, period_us=1000.0)
    t = np.array([100.0, 500.0])
    a = Renderer(maps, near, LAMBERTIAN()).image(t)
    b = Renderer(maps, ring, LAMBERTIAN()).image(t)
    np.testing.assert_allclose(a, b, atol=1e-4)
