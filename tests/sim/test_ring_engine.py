"""The simulator's compiled engine (``pstoolkit.sim.ring_engine``) against the event rule, the reference
engine (``Renderer`` + ``pstoolkit.sim.esim``) and dense frame integrals."""

from __future__ import annotations

import dataclasses
import tempfile
from pathlib import Path

import numba
import numpy as np
import pytest

import psfmt
from psfmt import EventArray
from pstoolkit.errors import UserError
from pstoolkit.events.rule import LOG_EPS, reference_time_us
from pstoolkit.optics.brdf import GGX, Lambertian
from pstoolkit.optics.lights import RingLight
from pstoolkit.plugin.options import defaults
from pstoolkit.sim import ring_engine
from pstoolkit.sim.config import SimulationConfig
from pstoolkit.sim.esim import simulate_events
from pstoolkit.sim.exposure import exposure_samples, integrate
from pstoolkit.sim.render import Renderer
from pstoolkit.sim.ring_kernels import inputs, lanes, shadow_table, tuning
from pstoolkit.sim.ring_kernels.inputs import FrameInputs, ShadowTable
from pstoolkit.sim.scenes import Blobs, Sphere
from pstoolkit.sim.sensor import EventSensor
from pstoolkit.sim.simulator import SHADOW_STEP_DEG, simulate

PERIOD_US = 30000.0
C = 0.15
MIN_DT_US = 20.0


def renderer(scene: object, brdf: object, size: int = 48, shadows: bool = True) -> Renderer:
    light = RingLight(elevation_deg=40.0, period_us=PERIOD_US, intensity=np.array([1.0, 0.9, 0.7]))
    step = PERIOD_US / exposure_samples(light, 0, PERIOD_US, SHADOW_STEP_DEG)
    maps = scene.build(size, 0, **defaults(scene.options))  # type: ignore[attr-defined]
    return Renderer(maps, light, brdf, shadows=shadows, shadow_step_us=step)


def run(r: Renderer, refractory_us: float = 0.0, **kwargs: object) -> tuple[EventArray, list[np.ndarray]]:
    blocks = list(ring_engine.simulate_ring(
        r, event_scale=0.5, t1_us=PERIOD_US, window_ends_us=[PERIOD_US / 3, 2 * PERIOD_US / 3, PERIOD_US],
        sensor=EventSensor(C, C, refractory_us=refractory_us), min_dt_us=MIN_DT_US, **kwargs,
    ))
    sums = [b.window_sums for b in blocks if b.window_sums is not None]
    return EventArray.concatenate([b.events for b in blocks]), sums


def true_log(r: Renderer, events: EventArray, t_us: np.ndarray) -> np.ndarray:
    width = r.maps.width // 2
    pixel = events.y.astype(np.int64) * width + events.x
    return np.log(r.event_pixels(t_us, pixel, 0.5) + LOG_EPS)


@pytest.mark.parametrize("refractory_us", [0.0, 1500.0])
def test_every_event_obeys_the_threshold_rule_against_the_true_irradiance(refractory_us: float) -> None:
    """L(t_k) − L_ref,k − p_k·C ≈ 0 for every event, the reference taken by the documented rule,
    within 2e-3 plus how far L moves within ``min_dt_us`` of t_k and of the reference time: a jump
    (a cast shadow's edge) is resolved to that step, and times are rounded to whole µs."""
    r = renderer(Blobs(), GGX())
    events, _ = run(r, refractory_us)
    assert len(events) > (5000 if refractory_us == 0 else 2000)
    width = r.maps.width // 2
    pixel = events.y.astype(np.int64) * width + events.x
    order = np.argsort(pixel, kind="stable")
    ev = events[order]
    first = np.ones(len(ev), dtype=bool)
    first[1:] = pixel[order][1:] != pixel[order][:-1]
    ref_time = np.zeros(len(ev))
    ref_time[~first] = reference_time_us(ev.t[:-1][~first[1:]], refractory_us)
    t = ev.t.astype(np.float64)
    residual = true_log(r, ev, t) - true_log(r, ev, ref_time) - ev.p * C

    def unresolved(times: np.ndarray) -> np.ndarray:
        return np.abs(true_log(r, ev, times + MIN_DT_US) - true_log(r, ev, times - MIN_DT_US))

    assert np.all(np.abs(residual) < 2e-3 + unresolved(t) + np.where(first, 0.0, unresolved(ref_time)))
    assert np.median(np.abs(residual)) < 1e-3


def test_events_match_the_reference_engine() -> None:
    """The same scene through ``pstoolkit.sim.esim`` with whole-frame renders and per-pixel refinement:
    the event counts agree within 1 % in total and within one event for most pixels."""
    r = renderer(Blobs(), GGX())
    events, _ = run(r)
    reference = EventArray.concatenate(list(simulate_events(
        lambda t: r.event_grey(t, 0.5), 0, PERIOD_US, width=24, height=24, sensor=EventSensor(C, C),
        min_dt_us=MIN_DT_US, render_pixels=lambda t, p: r.event_pixels(t, p, 0.5),
    )))
    assert abs(len(events) - len(reference)) <= 0.01 * len(reference)
    counts = [np.bincount(e.y.astype(np.int64) * 24 + e.x, minlength=24 * 24) for e in (events, reference)]
    assert np.mean(np.abs(counts[0] - counts[1]) <= 1) > 0.95


def test_exposure_sums_equal_a_dense_integral() -> None:
    """Each frame pixel's trapezoid sums on its event pixel's samples give the window's exposure
    within 0.5 % (of the brightest pixel) of a 10× denser midpoint integral."""
    r = renderer(Blobs(), GGX())
    _, sums = run(r)
    albedo = r.maps.albedo.reshape(-1, 3)[r.index]
    f0 = r.maps.f0.reshape(-1, 3)[r.index]
    intensity = r.light.intensity  # type: ignore[attr-defined]
    for k, window in enumerate(sums):
        a, b = k * PERIOD_US / 3, (k + 1) * PERIOD_US / 3
        samples = 10 * exposure_samples(r.light, a, b)
        (dense,) = integrate(r, a, b, samples)
        ours = (albedo * window[:, :1] + f0 * window[:, 1:]) * intensity * 1e-6
        expected = dense.reshape(-1, 3)[r.index]
        assert np.abs(ours - expected).max() < 0.005 * expected.max()


def test_a_lambertian_scene_has_no_specular_sum_and_no_shadows_means_none() -> None:
    r = renderer(Sphere(), Lambertian(), shadows=False)
    events, sums = run(r)
    assert len(events) > 1000 and all(np.all(s[:, 1] == 0) for s in sums)


def test_results_do_not_depend_on_room_threads_or_repetition() -> None:
    """Pixels that overflow their room in a block are run again from their state at its start:
    starting with room for one event gives the same events and exposure sums; so do one thread and
    a second run."""
    r = renderer(Blobs(), GGX())
    events, sums = run(r)
    small = run(r, capacity=1)
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        single = run(r)
    finally:
        numba.set_num_threads(threads)
    for other, other_sums in (small, single, run(r)):
        for name in ("x", "y", "t", "p"):
            np.testing.assert_array_equal(getattr(other, name), getattr(events, name))
        # bit-equal by construction: each event pixel is stepped by one thread, start to end, in the same
        # order of operations whatever the thread count or room (no cross-pixel sums, no fastmath)
        np.testing.assert_array_equal(np.stack(other_sums), np.stack(sums))
    assert np.all(np.diff(events.t) >= 0)


@pytest.mark.parametrize("sense", [1, -1])
def test_turning_the_light_step_by_step_follows_the_library_trigonometry(sense: int) -> None:
    """A lane turns the light's azimuth on from its last sample by each step (``turn``'s series):
    over 1000 steps of up to the longest step, ten turns either way round, it stays within 1e-13
    of cos and sin of the azimuth."""
    light = RingLight(elevation_deg=35.0, period_us=PERIOD_US, phase_deg=17.0, sense=sense)
    omega = inputs.ring_params(light)[3]
    steps = np.random.default_rng(3).uniform(0.0, PERIOD_US * tuning.MAX_STEP_TURNS, 1000)

    @numba.njit
    def walk(steps: np.ndarray, omega: float, azimuth: float) -> np.ndarray:
        c, s = np.cos(azimuth), np.sin(azimuth)
        out = np.empty((steps.size, 2))
        for i in range(steps.size):
            cos_d, sin_d = lanes.turn(omega * steps[i])
            c, s = c * cos_d - s * sin_d, s * cos_d + c * sin_d
            out[i] = c, s
        return out

    azimuth = np.radians(17.0) + omega * np.cumsum(steps)
    got = walk(steps, omega, np.radians(17.0))
    assert abs(azimuth[-1] - azimuth[0]) > 2 * np.pi * 10
    assert np.abs(got - np.stack([np.cos(azimuth), np.sin(azimuth)], axis=1)).max() < 1e-13


def test_the_lanes_log_is_the_library_log() -> None:
    """``log_lanes`` (a series, in SIMD) is within 4 ulp of ``np.log`` from 1e-300 to 1e300, and
    within 1.2e-16 where |ln x| < 1, around the engine's levels."""
    rng = np.random.default_rng(5)
    x = np.concatenate([10.0 ** rng.uniform(-300, 300, 4096), rng.uniform(0.4, 2.7, 4096), LOG_EPS * (1 + rng.random(4096)),
                        [1.0, 2.0, 0.5, np.sqrt(2.0), np.nextafter(np.sqrt(2.0), 2.0), LOG_EPS]])
    got = np.empty_like(x)
    lanes.log_lanes(x, got, np.empty(x.size, np.int64), np.empty(x.size, np.int64))
    expected = np.log(x)
    assert np.all(np.abs(got - expected) <= 4 * np.spacing(np.abs(expected)))
    small = np.abs(expected) < 1.0
    assert np.abs(got - expected)[small].max() < 1.2e-16


def test_only_shadows_on_lit_pixels_shorten_the_steps() -> None:
    """A sphere shadows itself only where it faces away from the light (the table has V < 1 there),
    so no pixel counts as reached by a cast shadow; the blobs cast shadows on lit pixels."""
    for scene, reached in ((Sphere(), False), (Blobs(), True)):
        r = renderer(scene, GGX())
        # the sphere declares that it casts no shadows; swept all the same, the table says so
        r = Renderer(dataclasses.replace(r.maps, self_shadowing=True), r.light, r.brdf, shadow_step_us=r.shadow_step_us)
        constants = inputs.frame_constants(ring_engine.shaded_scene(r))
        ring = inputs.ring_params(r.light)  # type: ignore[arg-type]
        block_us = tuning.BLOCK_GRID_STEPS * r.shadow_step_us  # type: ignore[operator]
        shadowed, lit_shadowed = False, False
        for ta in np.arange(0.0, PERIOD_US, block_us):
            openness, column_major, grid = shadow_table.sweep_rows(ring_engine.cast_shadows(r), ta, min(ta + block_us, PERIOD_US))
            reach = shadow_table.lit_shadow(constants.values, r.index, r.column_major_index, ring[1], openness,
                                          column_major, shadow_table.grid_light(ring, openness.shape[0], grid))
            shadowed |= bool((openness < 1.0).any())
            lit_shadowed |= bool(reach.any())
        assert shadowed
        assert lit_shadowed == reached


def test_lit_shadow_bits_follow_their_definition() -> None:
    """Bit i of a frame pixel's mask is set exactly where V < 1 at grid time i or i + 1 while the
    light is on the pixel's side (n·l above minus the slack) at that grid time or one next to it;
    checked on a table of all ``TABLE_ROWS`` grid times, with row- and column-major rows."""
    r = renderer(Blobs(), GGX())
    step = float(r.shadow_step_us)  # type: ignore[arg-type]
    openness, column_major, grid = shadow_table.sweep_rows(ring_engine.cast_shadows(r), 0.5 * step, 62.3 * step)
    rows = openness.shape[0]
    assert rows == tuning.TABLE_ROWS
    assert column_major.any() and not column_major.all()
    constants = inputs.frame_constants(ring_engine.shaded_scene(r))
    ring = inputs.ring_params(r.light)  # type: ignore[arg-type]
    light = shadow_table.grid_light(ring, rows, grid)
    reach = shadow_table.lit_shadow(constants.values, r.index, r.column_major_index, ring[1], openness, column_major,
                                  light)
    v = np.where(column_major[:, None], openness[:, r.column_major_index], openness[:, r.index])
    n = constants.values
    nl = n[:, inputs.NX] * light[0][:, None] + n[:, inputs.NY] * light[1][:, None] + n[:, inputs.NZ] * ring[1]
    lit = nl > -light[2][:, None]
    near = lit.copy()
    near[1:] |= lit[:-1]
    near[:-1] |= lit[1:]
    shaded = (v < 1.0) & near
    intervals = shaded[:-1] | shaded[1:]
    expected = (intervals.astype(np.uint64) << np.arange(rows - 1, dtype=np.uint64)[:, None]).sum(axis=0, dtype=np.uint64)
    # bits of thresholds on n·l summed in the kernel's order (numba without fastmath contracts no FMA),
    # so the same doubles are compared on both sides
    np.testing.assert_array_equal(reach[r.index], expected)
    assert np.count_nonzero(reach) == np.count_nonzero(expected) > 50
    # the shadows' last interval and masks that are not all one
    assert (expected >> np.uint64(rows - 2)).any()
    assert (expected != (np.uint64(1) << np.uint64(rows - 1)) - np.uint64(1)).any()
    longer = shadow_table.sweep_rows(ring_engine.cast_shadows(r), 0.5 * step, 63.3 * step)
    with pytest.raises(ValueError, match="more than TABLE_ROWS"):
        shadow_table.lit_shadow(constants.values, r.index, r.column_major_index, ring[1], longer[0], longer[1],
                              shadow_table.grid_light(ring, longer[0].shape[0], longer[2]))


def test_shading_reads_the_table_only_where_the_bits_say_it_matters() -> None:
    """A lane reads V only in the table intervals its pixels' ``lit_shadow`` bits mark; at random
    times through a blobs block, every lane's shading equals that with V read in every interval."""
    r = renderer(Blobs(), GGX())
    step = float(r.shadow_step_us)  # type: ignore[arg-type]
    ta, tb = 3.2 * step, 61.7 * step
    openness, column_major, grid = shadow_table.sweep_rows(ring_engine.cast_shadows(r), ta, tb)
    constants = inputs.frame_constants(ring_engine.shaded_scene(r))
    feet = inputs.footprints(*(a.cpu().numpy() for a in r.footprint(0.5)), r.pixels)
    ring = inputs.ring_params(r.light)  # type: ignore[arg-type]
    reach = shadow_table.lit_shadow(constants.values, r.index, r.column_major_index, ring[1], openness, column_major,
                                  shadow_table.grid_light(ring, openness.shape[0], grid))
    slots = lanes.idle_lanes(constants.values.shape[1], feet.pixel.shape[1])
    frame = FrameInputs(constants.values, feet.weight, feet.pixel, r.index, r.column_major_index, True)
    table = ShadowTable(openness, column_major, *grid, reach)
    width = tuning.LANES
    rng = np.random.default_rng(5)
    skipped = 0
    for first in range(0, feet.pixel.shape[0], width):
        shadows = np.zeros(width, np.uint64)
        for k in range(width):
            lanes.load_lane(slots, k, first + k, frame)
            for q in range(feet.pixel.shape[1]):
                if feet.pixel[first + k, q] >= 0:
                    shadows[k] |= reach[slots.position[q, k]]
        t1 = rng.uniform(ta, tb, width)
        azimuth = ring[2] + ring[3] * (t1 - ring[4])
        results = []
        for bits in (shadows, np.full(width, np.uint64(0xFFFFFFFFFFFFFFFF))):
            now, grey = np.empty((2, feet.pixel.shape[1], width)), np.empty(width)
            lanes.shade_lanes(t1, np.cos(azimuth), np.sin(azimuth), slots, bits, True, ring, table, LOG_EPS, now, grey)
            results.append((now, grey))
        # bit-equal: where the skipped intervals are, V ≥ 1 and the same arithmetic gives the same doubles
        np.testing.assert_array_equal(results[0][0], results[1][0])
        np.testing.assert_array_equal(results[0][1], results[1][1])
        row = np.clip(np.floor(t1 / grid[0] - grid[1]).astype(np.int64), 0, openness.shape[0] - 2)
        skipped += int(np.count_nonzero((shadows >> row.astype(np.uint64)) & np.uint64(1) == 0))
    # most lanes skip the table; the check is not empty: V < 1 somewhere in the table
    assert skipped > 0.5 * feet.pixel.shape[0]
    assert (openness < 1.0).any() and reach.any()


def test_blocks_fit_the_shadow_masks() -> None:
    """However long the blocks are asked to be, and where a window leaves a stretch past the last
    whole block, no block is longer than ``TABLE_ROWS`` − 3 grid intervals (its table fits the
    masks' bits) and every window ends on a block's end."""
    r = renderer(Blobs(), GGX(), size=32)
    step = float(r.shadow_step_us)  # type: ignore[arg-type]
    window_ends = [70.5 * step, 131.0 * step, PERIOD_US]
    blocks = list(ring_engine.simulate_ring(
        r, event_scale=0.5, t1_us=PERIOD_US, window_ends_us=window_ends, sensor=EventSensor(C, C),
        min_dt_us=MIN_DT_US, block_us=1e9,
    ))
    ends = [b.t_end_us for b in blocks]
    assert max(np.diff([0.0, *ends])) <= (tuning.TABLE_ROWS - 3) * step * (1 + 1e-12)
    assert set(window_ends) <= set(ends)
    assert sum(len(b.events) for b in blocks) > 1000


def test_a_sphere_without_self_shadowing_is_simulated_as_with_it() -> None:
    """The sphere declares no self-shadowing, so no shadow table is swept for it; swept all the same,
    its events and window sums are the same bytes (a convex surface shadows only where it is unlit)."""
    r = renderer(Sphere(), GGX())
    assert not r.maps.self_shadowing and not r.shadows
    swept = Renderer(dataclasses.replace(r.maps, self_shadowing=True), r.light, r.brdf, shadow_step_us=r.shadow_step_us)
    assert swept.shadows
    events, sums = run(r)
    swept_events, swept_sums = run(swept)
    assert len(events) > 5000
    # bit-equal: where the swept table could shadow, the pixel faces away from the light, and elsewhere
    # V ≥ 1 leaves the same arithmetic
    for c in "xytp":
        np.testing.assert_array_equal(getattr(events, c), getattr(swept_events, c))
    for a, b in zip(sums, swept_sums, strict=True):
        np.testing.assert_array_equal(a, b)


def test_supported_only_for_the_closed_form_on_the_cpu() -> None:
    class OtherGGX(GGX):
        """Another BRDF type: shaded through ``brdf.shade``."""

    assert ring_engine.supported(renderer(Blobs(), GGX()))
    assert not ring_engine.supported(renderer(Blobs(), OtherGGX()))


def test_the_simulator_gives_the_same_capture_through_either_engine(monkeypatch: pytest.MonkeyPatch) -> None:
    """``pstoolkit simulate`` with the compiled engine and with the reference one (as for a plugin
    BRDF): events within 1 %, frames within 0.5 % of full scale."""
    config = SimulationConfig(scene="blobs", size=48, bit_depth=16, refractory_us=500.0)
    with tempfile.TemporaryDirectory() as tmp:
        fast = simulate(config, Path(tmp) / "fast.h5")
        monkeypatch.setattr(ring_engine, "supported", lambda _: False)
        slow = simulate(config, Path(tmp) / "slow.h5")
        assert abs(fast.events - slow.events) <= 0.01 * slow.events
        a, b = psfmt.load(fast.path), psfmt.load(slow.path)
        frames_a, frames_b = a.frames.data.astype(np.float64), b.frames.data.astype(np.float64)
        assert np.abs(frames_a - frames_b).max() < 0.005 * 65535


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"sensor": EventSensor(contrast_pos=0.0)}, "simulate_ring: contrast_pos must be a positive number, got 0.0"),
    ({"sensor": EventSensor(refractory_us=-1.0)}, "simulate_ring: refractory_us must be zero or positive, got -1.0"),
    ({"min_dt_us": 0.0}, "simulate_ring: min_dt_us must be a positive number, got 0.0"),
    ({"window_ends_us": [0.0]}, r"simulate_ring: window ends must lie in \(0, t1_us = 30000.0\]"),
])
def test_bad_options_name_the_option(kwargs: dict, message: str) -> None:
    arguments = {"event_scale": 0.5, "t1_us": PERIOD_US, "window_ends_us": [PERIOD_US], "sensor": EventSensor(C, C),
                 **kwargs}
    with pytest.raises(UserError, match=message):
        next(ring_engine.simulate_ring(renderer(Sphere(), GGX(), size=16), **arguments))


def test_a_shadowed_pixel_steps_short_only_around_its_shadows() -> None:
    """With a shadow in grid interval 3 (µs 300–400 on a 100 µs grid), steps reach up to it, take one
    grid interval near and inside it, and are long again after it; no shadow: always long."""
    table = ShadowTable(np.ones((2, 1), np.float32), np.zeros(2, np.bool_), 100.0, 0.0, np.zeros(1, np.uint64))
    room = numba.njit(lambda t, bits, table: shadow_table.shadow_room(t, bits, table, 100.0, 1000.0))
    bits = np.uint64(1 << 3)
    assert room(50.0, bits, table) == 250.0
    assert room(250.0, bits, table) == 100.0
    assert room(320.0, bits, table) == 100.0
    assert room(450.0, bits, table) == 1000.0
    assert room(50.0, np.uint64(0), table) == 1000.0
    # a step reaches the next marked interval however far, within the longest step
    far = numba.njit(lambda t, bits, table: shadow_table.shadow_room(t, bits, table, 100.0, 1e9))
    assert far(50.0, np.uint64(1 << 40), table) == 3950.0
    assert far(450.0, np.uint64((1 << 40) | (1 << 3)), table) == 3550.0
    assert far(6050.0, np.uint64(1 << 63), table) == 250.0
