"""The simulator's compiled engine: events and long exposures of a scene under a ring light in one
pass per event pixel (numba, in parallel over event pixels).

It covers what the simulator renders on the CPU with the built-in BRDFs (``ggx``, ``lambertian``):
a directional ring light, the closed-form shading of ``Renderer`` and the cast shadows of its shadow
grid. Other BRDFs, and other devices, go through ``Renderer`` and ``pstoolkit.sim.esim``; both follow the
same event rule (``pstoolkit.events.rule``) and ``tests/sim/test_ring_engine.py`` compares them.

Per event pixel, time advances in its own steps (ESIM's adaptive sampling, made per pixel): a step
whose change of the pixel's ``L = ln(I + ε)`` exceeds ``max_dlog`` (half the contrast) is shortened
until it does not or is ``min_dt_us`` long, and the next step grows or shrinks with the change of
this one, up to ``max_dt_us`` (8° of the turn), and around the intervals of the shadow grid in
which a cast shadow falls on the pixel while it is lit, up to one interval, so no sweep is stepped
over; L may also leave the previous step's line by at most ``MAX_BEND``. ``I`` is the area average
of the frame pixels under the event pixel, each shaded in closed form at the step's time; crossings
are placed exactly on the line between samples, by either refractory rule of
``pstoolkit.events.rule`` ("reset-at-end" and "rate-limited", ``ring_kernels.firing``). Each frame
pixel belongs to the event pixel covering most of it, and its ∫ V·[n·l]₊ dt and ∫ V·[n·l]₊·ratio dt
(``ratio`` the GGX specular factor) accumulate by the trapezoid rule on that pixel's samples, in
its slot of the owner's footprint: the exposures come from the same shading as the events.

Work per event pixel is about (number of steps) × (frame pixels under it): a pixel that sees no
change takes ``max_dt_us`` steps, one that fires takes about three steps per event. A thread steps
``LANES`` pixels at once, each lane's state at its index of arrays across the lanes, so shading, log,
step control and firing rule run as SIMD loops (``ring_kernels.lanes``: a series for ln, and the
light's azimuth turned on from the lane's last sample by a series for cos and sin); a lane takes its
pixel's frame-pixel constants and sums ((E, K, 2), one per slot of its footprint) and gives the sums
back when the pixel is done. The kernels live in ``pstoolkit.sim.ring_kernels``, one module a job.
Memory: the per-pixel state, a cast-shadow table for the current block of time, and the block's events
(room for ``FIRST_ROOM`` per pixel at first, within ``ROOM_BYTES``, then for as many as the busiest
pixel needed so far; pixels that overflow it are run again from their state at the block's start).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import numba
import numpy as np

from psfmt import EventArray
from pstoolkit.errors import UserError
from pstoolkit.grid import event_shape
from pstoolkit.optics.brdf import GGX
from pstoolkit.optics.lights import RingLight
from pstoolkit.sim.esim import irradiance_on_lines
from pstoolkit.sim.event_noise import NoiseEvents, merge_sorted, static_leak
from pstoolkit.sim.render import Renderer
from pstoolkit.sim.ring_kernels.inputs import (
    EventRoom,
    EventRule,
    PixelState,
    ShadedScene,
    StepLimits,
    footprints,
    frame_constants,
    frame_inputs,
    owner_slots,
    ring_params,
)
from pstoolkit.sim.ring_kernels.output import gather
from pstoolkit.sim.ring_kernels.shadow_table import CastShadows, block_table
from pstoolkit.sim.ring_kernels.stepper import advance, start
from pstoolkit.sim.ring_kernels.tuning import BLOCK_GRID_STEPS, FIRST_ROOM, MAX_STEP_TURNS, ROOM_BYTES, TABLE_ROWS
from pstoolkit.sim.sensor import EventSensor, check_sampling

__all__ = ["Block", "cast_shadows", "shaded_scene", "simulate_ring", "supported"]


@dataclass
class Block:
    """What one block of time produced: its events (sorted by µs, then pixel), its end, and — when a
    window of ``window_ends_us`` ends with it — that window's (P, 2) sums ∫ V·[n·l]₊ dt and
    ∫ V·[n·l]₊·ratio dt per masked frame pixel (dt in µs)."""

    events: EventArray
    t_end_us: float
    window_sums: np.ndarray | None


def shaded_scene(renderer: Renderer) -> ShadedScene:
    """What the kernels take of ``renderer``'s scene, light and BRDF (``ShadedScene``)."""
    constants, rgb = renderer.closed_form_constants()
    return ShadedScene(constants, rgb, np.asarray(renderer.light.intensity, dtype=np.float64),  # type: ignore[attr-defined]
                       isinstance(renderer.brdf, GGX), renderer.index, renderer.column_major_index,
                       renderer.maps.height, renderer.maps.width)


def cast_shadows(renderer: Renderer) -> CastShadows:
    """What the shadow table takes of ``renderer``'s cast shadows (``CastShadows``)."""
    return CastShadows(renderer.shadows, renderer.shadow_step_us, renderer.frame_openness, renderer.maps.height * renderer.maps.width)


def supported(renderer: Renderer) -> bool:
    """Whether ``simulate_ring`` can render this renderer's scene: a ring light, the ``ggx`` or
    ``lambertian`` BRDF in closed form, on the CPU, with cast shadows on a shadow grid (or none)."""
    return (
        isinstance(renderer.light, RingLight)
        and renderer.event_pixels_supported
        and renderer.device.type == "cpu"
    )


def _block_spans(ends: list[float], block_us: float, longest_us: float) -> list[tuple[float, float]]:
    """The blocks of time (start, end) in µs, in order: ``block_us`` long, ending on each of ``ends``
    (the windows'); a window's last stretch shorter than a quarter block joins the block before when
    that stays within ``longest_us``."""
    spans = []
    ta = 0.0
    for end in ends:
        while ta < end:
            tb = min(end, ta + block_us)
            if end - tb < 0.25 * block_us and end - ta <= longest_us:
                tb = end
            spans.append((ta, tb))
            ta = tb
    return spans


def _widen(room: EventRoom) -> EventRoom:
    """More room for a block's events: half again the busiest pixel's count."""
    most = int(room.count.max())
    capacity = most + most // 2
    n_events, width = room.t_us.shape
    return EventRoom(
        np.concatenate([room.t_us, np.empty((n_events, capacity - width), np.int64)], axis=1),
        np.concatenate([room.polarity, np.empty((n_events, capacity - width), np.int8)], axis=1),
        room.count,
    )


def simulate_ring(
    renderer: Renderer,
    *,
    event_scale: float,
    t1_us: float,
    window_ends_us: list[float],
    sensor: EventSensor | None = None,
    min_dt_us: float = 1.0,
    max_dt_us: float | None = None,
    max_dlog: float | None = None,
    block_us: float | None = None,
    capacity: int | None = None,
) -> Iterator[Block]:
    """Events of the event sensor at ``event_scale`` over [0, ``t1_us``] and the exposure sums of the
    windows ending at ``window_ends_us``, block by block in time order (see the module docstring).

    Parameters
    ----------
    renderer
        The scene, light and BRDF; must be ``supported``.
    event_scale
        Event pixels per frame pixel, in (0, 1].
    t1_us
        The end of the simulation, µs (it starts at 0).
    window_ends_us
        Ends of the exposure windows, increasing, inside (0, t1_us], µs: a ``Block`` ends on each and
        carries the window's sums.
    sensor
        The event sensor (default ``EventSensor()``); thresholds are drawn as
        ``pstoolkit.sim.esim.simulate_events`` draws them, and its noise as there: the leak as a drift
        of each pixel's L (pixels that see no frame pixel leak in closed form), shot noise and hot
        pixels by ``pstoolkit.sim.event_noise.NoiseEvents`` block by block.
    min_dt_us, max_dt_us
        Shortest and longest step, µs; the longest (away from the shadow-grid intervals in which a cast
        shadow falls on the pixel while it is lit; around those it steps at most one) defaults to
        ``MAX_STEP_TURNS`` of the turn.
    max_dlog
        Largest change of L a step may make (default half the smaller threshold).
    block_us
        Length of a block of time, µs (default ``BLOCK_GRID_STEPS`` shadow-grid intervals; at most
        ``TABLE_ROWS`` − 3).
    capacity
        First room for events per pixel and block, widened as needed (default ``FIRST_ROOM`` within
        ``ROOM_BYTES``).

    Raises
    ------
    UserError
        The renderer is not supported, or an option is out of range.
    """
    if not supported(renderer):
        raise UserError("simulate_ring needs a ring light, the ggx or lambertian BRDF, the CPU and a shadow grid")
    light = renderer.light
    assert isinstance(light, RingLight)
    sensor = EventSensor() if sensor is None else sensor
    if max_dlog is None:
        max_dlog = sensor.half_contrast()
    height, width = event_shape(renderer.maps.height, renderer.maps.width, event_scale)
    sensor.check("simulate_ring")
    check_sampling("simulate_ring", 0.0, t1_us, width, height, {"max_dlog": max_dlog, "min_dt_us": min_dt_us})
    ends = sorted({float(t) for t in window_ends_us} | {float(t1_us)})
    if ends[0] <= 0 or ends[-1] > t1_us:
        raise UserError(f"simulate_ring: window ends must lie in (0, t1_us = {t1_us}]")
    grid_dt_us = float(renderer.shadow_step_us or light.period_us / 360.0)
    if max_dt_us is None:
        max_dt_us = light.period_us * MAX_STEP_TURNS
    longest_us = (TABLE_ROWS - 3) * grid_dt_us
    block_us = min(BLOCK_GRID_STEPS * grid_dt_us if block_us is None else float(block_us), longest_us)
    scene, cast = shaded_scene(renderer), cast_shadows(renderer)
    feet = footprints(*(a.cpu().numpy() for a in renderer.footprint(event_scale)), renderer.pixels)
    frame = frame_inputs(scene, frame_constants(scene), feet)
    owner = owner_slots(feet)
    n_events = height * width
    c_pos, c_neg = sensor.thresholds(n_events)
    leak_per_us = sensor.leak_per_us(c_pos)
    rule = EventRule(c_pos, c_neg, float(sensor.refractory_us), sensor.paced, float(sensor.eps), leak_per_us,
                     sensor.leak_hz > 0)
    limits = StepLimits(float(max_dlog), float(min_dt_us), float(max_dt_us), grid_dt_us)
    ring = ring_params(light)
    spans = _block_spans(ends, block_us, longest_us)
    # the first block's table serves the start too
    table = block_table(cast, *spans[0], frame, ring)
    state = PixelState(
        level=np.empty(n_events), hi=np.empty(n_events), lo=np.empty(n_events),
        blind_until_us=np.full(n_events, -np.inf if rule.paced else np.inf),
        step_us=np.full(n_events, max_dt_us / 4.0), slope=np.full(n_events, np.nan),
        shade=np.zeros((*feet.pixel.shape, 2)), sums=np.zeros((*feet.pixel.shape, 2)),
    )
    start(0.0, frame, ring, table, cast.shadows, rule.eps, state)
    leak_start = sensor.leak_start(c_pos)
    state.hi[:] = state.level - leak_start + c_pos
    state.lo[:] = state.level - leak_start - c_neg
    noise = NoiseEvents(sensor, width, height, c_pos, c_neg) if sensor.fires_noise else None
    # event pixels over no frame pixel are never stepped: they see no light, and leak in closed form
    dark = frame.pixel[:, 0] < 0
    unlit = np.flatnonzero(dark) if sensor.leak_hz > 0 else np.empty(0, np.int64)
    if capacity is None:
        capacity = min(FIRST_ROOM, ROOM_BYTES // (9 * n_events))
    capacity = max(1, int(capacity))
    room = EventRoom(np.empty((n_events, capacity), np.int64), np.empty((n_events, capacity), np.int8),
                     np.zeros(n_events, np.int64))
    everyone = np.arange(n_events)
    for block, (ta, tb) in enumerate(spans):
        if block and cast.shadows:
            table = block_table(cast, ta, tb, frame, ring)
        level_start = state.level.copy() if noise is not None else None
        order = everyone
        while True:
            advance(order, ta, tb, frame, ring, table, rule, limits, state, room, numba.get_num_threads())
            order = np.flatnonzero(room.count > room.t_us.shape[1])
            if order.size == 0:
                break
            # pixels fired more than there was room for: widen the room and run them again
            room = _widen(room)
        x, y, t, p = gather(room.t_us, room.polarity, room.count, width, math.floor(ta + 0.5), math.floor(tb + 0.5))
        events = EventArray(x=x, y=y, t=t, p=p)
        if unlit.size:
            pix, t_us = static_leak(unlit, leak_per_us, leak_start, c_pos, sensor, ta, tb)
            events = merge_sorted(events, pix, t_us, np.ones(pix.size, np.int8), width)
        if noise is not None:
            lines = np.stack([level_start, state.level])
            lines[:, dark] = math.log(sensor.eps)
            events = noise.merge(ta, tb, events, irradiance_on_lines(np.array([ta, tb]), lines, leak_per_us, 0.0, sensor.eps))
        sums = None
        if tb in window_ends_us:
            sums = np.take(state.sums.reshape(-1, 2), owner, axis=0)
            state.sums[:] = 0.0
        yield Block(events, tb, sums)
