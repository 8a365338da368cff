"""The simulator's fast rendering paths against the reference ones: closed-form shading against
``brdf.shade``, shadows on a time grid against exact sweeps, single event pixels against whole
event frames, and per-pixel refinement of the event generator."""

from __future__ import annotations

import numpy as np
import pytest
from helpers.esim import PERIOD_US, SIZE, sine_scene, threshold_residuals

from psfmt import EventArray
from pstoolkit.errors import UserError
from pstoolkit.optics.brdf import GGX, Lambertian
from pstoolkit.optics.lights import RingLight
from pstoolkit.plugin.options import defaults
from pstoolkit.sim.esim import simulate_events
from pstoolkit.sim.exposure import exposure_samples, integrate
from pstoolkit.sim.render import Renderer
from pstoolkit.sim.scenes import Blobs, Relief, Sphere
from pstoolkit.sim.sensor import EventSensor


class GenericGGX(GGX):
    """GGX under another type: the renderer shades it through ``brdf.shade``, the reference path."""


class GenericLambertian(Lambertian):
    """Lambertian under another type (reference path)."""


PERIOD = 30000.0


def light() -> RingLight:
    return RingLight(elevation_deg=35.0, period_us=PERIOD, intensity=np.array([1.0, 0.9, 0.7]))


@pytest.mark.parametrize(("scene", "options"), [
    (Sphere, {"roughness": 0.05, "f0": 0.5}),
    (Blobs, {}),
    (Relief, {"varying": True}),
])
def test_closed_form_shading_is_brdf_shade(scene: type, options: dict) -> None:
    maps = scene().build(40, 2, **{**defaults(scene.options), **options})
    t = np.linspace(0.0, PERIOD, 7)
    for fast, generic in ((GGX(), GenericGGX()), (Lambertian(), GenericLambertian())):
        a = Renderer(maps, light(), fast).image(t)
        b = Renderer(maps, light(), generic).image(t)
        np.testing.assert_allclose(a, b, rtol=2e-4, atol=1e-6 * b.max())
        (sum_a, diffuse_a) = integrate(Renderer(maps, light(), fast), 0, 10000, brdfs=[fast, Lambertian()])
        (sum_b, diffuse_b) = integrate(Renderer(maps, light(), generic), 0, 10000, brdfs=[generic, GenericLambertian()])
        np.testing.assert_allclose(sum_a, sum_b, rtol=2e-4, atol=1e-6 * sum_b.max())
        np.testing.assert_allclose(diffuse_a, diffuse_b, rtol=2e-4, atol=1e-6 * diffuse_b.max())


def grid_step(degrees: float) -> float:
    return PERIOD / exposure_samples(light(), 0, PERIOD, degrees)


def test_shadow_grid_is_exact_on_the_grid_and_keeps_frames_within_half_a_percent() -> None:
    maps = Blobs().build(48, 1, **defaults(Blobs.options))
    step = grid_step(1.0)
    exact = Renderer(maps, light(), GGX())
    grid = Renderer(maps, light(), GGX(), shadow_step_us=step)
    on_grid = np.arange(0, 40) * step * 3
    np.testing.assert_allclose(grid.image(on_grid), exact.image(on_grid), rtol=1e-6, atol=1e-7)
    n = exposure_samples(light(), 0, 10000)
    (dense,) = integrate(exact, 0, 10000, samples=10 * n)
    (frame,) = integrate(grid, 0, 10000)
    assert np.abs(frame - dense).max() < 0.005 * dense.max()
    # a coarser grid blurs the shadows more: the step matters, so the test can fail
    (coarse,) = integrate(Renderer(maps, light(), GGX(), shadow_step_us=grid_step(8.0)), 0, 10000)
    assert np.abs(coarse - dense).max() > 2 * np.abs(frame - dense).max()


def _row_major(renderer: Renderer, table: np.ndarray, column_major: np.ndarray) -> np.ndarray:
    """``frame_openness``'s rows, the column-major ones transposed back to row-major."""
    h, w = renderer.maps.height, renderer.maps.width
    return np.stack([row.reshape(w, h).T.ravel() if major else row for row, major in zip(table, column_major)])


def test_frame_openness_in_the_reused_buffer_equals_a_fresh_sweep() -> None:
    """``grid_openness`` sweeps each grid time anew; ``frame_openness`` sweeps into the renderer's
    buffer, and reusing it for other times changes nothing. Its rows of lights that run more along
    the image rows than its columns are column-major, the others row-major."""
    maps = Blobs().build(48, 1, **defaults(Blobs.options))
    keys = [np.arange(0, 12), np.arange(40, 45), np.arange(100, 112)]
    fresh = [Renderer(maps, light(), GGX(), shadow_step_us=grid_step(1.0)).grid_openness(k) for k in keys]
    reused = Renderer(maps, light(), GGX(), shadow_step_us=grid_step(1.0))
    buffer, _ = reused.frame_openness(keys[0])
    for k, expected in zip(keys, fresh):
        got, column_major = reused.frame_openness(k)
        assert np.shares_memory(got, buffer)
        direction, _ = reused.light.evaluate(k * grid_step(1.0))
        np.testing.assert_array_equal(column_major, np.abs(direction[:, 0]) >= np.abs(direction[:, 1]))
        # bit-equal: the same sweeps (no fastmath) written into a reused buffer, some rows transposed
        np.testing.assert_array_equal(_row_major(reused, got, column_major)[:, reused.index], expected)
        np.testing.assert_array_equal(got[column_major][:, reused.column_major_index], expected[column_major])
    assert (fresh[0] < 1.0).any() and (fresh[0] >= 1.0).any()


def test_frame_openness_holds_every_frame_pixel() -> None:
    """``frame_openness`` is ``grid_openness`` at the masked pixels' flat positions; pixels outside
    the mask (a sphere's corners) are open."""
    renderer = Renderer(Sphere().build(40, 0, **defaults(Sphere.options)), light(), GGX(), shadow_step_us=grid_step(1.0))
    keys = np.arange(30, 70)
    table, column_major = renderer.frame_openness(keys)
    assert table.shape == (40, 40 * 40) and renderer.pixels < 40 * 40
    assert column_major.any() and not column_major.all()
    frame = _row_major(renderer, table, column_major)
    # bit-equal: both run the same sweeps on the same times; only the storage order differs
    np.testing.assert_array_equal(frame[:, renderer.index], renderer.grid_openness(keys))
    assert (np.delete(frame, renderer.index, axis=1) > 1.0).all()
    assert (frame[:, renderer.index] < 1.0).any()


@pytest.mark.parametrize("event_scale", [0.5, 0.4])
def test_single_event_pixels_equal_the_event_frame(event_scale: float) -> None:
    maps = Blobs().build(40, 3, **defaults(Blobs.options))
    renderer = Renderer(maps, light(), GGX(), shadow_step_us=grid_step(1.0))
    assert renderer.event_pixels_supported
    t = np.array([0.0, 1234.5, 7000.0, 22222.0])
    frames = renderer.event_grey(t, event_scale)
    rng = np.random.default_rng(0)
    which = rng.integers(0, len(t), 300)
    pixel = rng.integers(0, frames[0].size, 300)
    single = renderer.event_pixels(t[which], pixel, event_scale)
    np.testing.assert_allclose(single, frames.reshape(len(t), -1)[which, pixel], rtol=1e-9, atol=1e-12)
    assert single.max() > 0.1


def test_event_pixels_need_a_shadow_grid_and_a_closed_form_brdf() -> None:
    maps = Blobs().build(32, 0, **defaults(Blobs.options))
    assert not Renderer(maps, light(), GGX()).event_pixels_supported
    assert not Renderer(maps, light(), GenericGGX(), shadow_step_us=100.0).event_pixels_supported
    assert Renderer(maps, light(), Lambertian(), shadows=False).event_pixels_supported
    with pytest.raises(UserError, match="event_pixels needs a directional light"):
        Renderer(maps, light(), GGX()).event_pixels(np.zeros(1), np.zeros(1, np.int64), 0.5)


def pixel_render(render):
    calls = {"pixels": 0}

    def render_pixels(t_us: np.ndarray, pixel: np.ndarray) -> np.ndarray:
        calls["pixels"] += len(t_us)
        return render(t_us).reshape(len(t_us), -1)[np.arange(len(t_us)), pixel]

    return render_pixels, calls


@pytest.mark.parametrize("refractory_us", [0.0, 30_000.0])
def test_per_pixel_refinement_keeps_the_threshold_rule_and_the_counts(refractory_us: float) -> None:
    """Each pixel is sampled so that its own |ΔL| stays under max_dlog = C/2: the residual of the
    threshold rule is then bounded by the curvature of L over such a step (here < 5e-3), and the
    event count matches frame-wise refinement within 1 %."""
    render, *_ = sine_scene(static_columns=4)
    render_pixels, calls = pixel_render(render)
    frames: list[int] = []

    def counted(t_us: np.ndarray) -> np.ndarray:
        frames.append(len(t_us))
        return render(t_us)

    kwargs = {"width": SIZE, "height": SIZE, "sensor": EventSensor(refractory_us=refractory_us)}
    fine = EventArray.concatenate(list(simulate_events(counted, 0, PERIOD_US, render_pixels=render_pixels, **kwargs)))
    full = EventArray.concatenate(list(simulate_events(render, 0, PERIOD_US, **kwargs)))
    assert abs(len(fine) - len(full)) <= 0.01 * len(full)
    assert np.abs(threshold_residuals(render, fine, 0, refractory_us)).max() < 5e-3
    assert calls["pixels"] > 0 and fine.x.min() == 4


def test_per_pixel_refinement_renders_few_full_frames_for_a_moving_edge() -> None:
    """A sharp edge sweeping a 64×64 sensor: only the pixels it crosses need fine samples, so far
    fewer whole frames are rendered for the same events."""
    size, span_us = 64, 10_000.0
    speed = size / span_us  # columns per µs

    def edge(t_us: np.ndarray) -> np.ndarray:
        x = np.arange(size)[None, None, :]
        position = speed * np.asarray(t_us, dtype=np.float64)[:, None, None]
        return np.broadcast_to(1.0 + 50.0 / (1.0 + np.exp(np.clip((x - position) / 0.05, -50.0, 50.0))), (len(t_us), size, size))

    render_pixels, calls = pixel_render(edge)
    counts = {"fine": 0, "full": 0}

    def counted(key: str):
        def render(t_us: np.ndarray) -> np.ndarray:
            counts[key] += len(t_us)
            return edge(t_us)
        return render

    kwargs = {"width": size, "height": size, "min_dt_us": 1.0}
    fine = EventArray.concatenate(list(simulate_events(counted("fine"), 0, span_us, render_pixels=render_pixels, **kwargs)))
    full = EventArray.concatenate(list(simulate_events(counted("full"), 0, span_us, **kwargs)))
    assert abs(len(fine) - len(full)) <= 0.01 * len(full)
    assert counts["fine"] * 3 < counts["full"]
    assert calls["pixels"] < counts["full"] * size * size / 50


def test_bad_render_pixels_output() -> None:
    render, *_ = sine_scene()
    with pytest.raises(UserError, match=r"render_pixels returned shape \(1,\), expected \("):
        list(simulate_events(render, 0, PERIOD_US, width=SIZE, height=SIZE, render_pixels=lambda t, p: np.ones(1)))


def test_fixed_sample_times_are_the_only_whole_frame_renders() -> None:
    render, *_ = sine_scene()
    render_pixels, _ = pixel_render(render)
    seen: list[np.ndarray] = []

    def counted(t_us: np.ndarray) -> np.ndarray:
        seen.append(np.array(t_us))
        return render(t_us)

    grid = np.linspace(0.0, PERIOD_US, 401)[1:-1]
    kwargs = {"width": SIZE, "height": SIZE, "render_pixels": render_pixels}
    events = EventArray.concatenate(list(simulate_events(counted, 0, PERIOD_US, sample_times_us=grid, **kwargs)))
    # bit-equal: the render is called with the given sample times themselves, not recomputed ones
    np.testing.assert_array_equal(np.concatenate(seen), np.concatenate(([0.0], grid, [PERIOD_US])))
    assert np.abs(threshold_residuals(render, events, 0, 0.0)).max() < 5e-3
    with pytest.raises(UserError, match=r"sample_times_us must increase strictly inside \(t0_us, t1_us\)"):
        next(simulate_events(render, 0, PERIOD_US, sample_times_us=grid[::-1], **kwargs))
