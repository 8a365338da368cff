"""The simulator: renders a registered scene under a ring light and writes a hybrid capture.

A hybrid capture (the default) holds ``frames`` long exposures per light period, each integrating the
irradiance over a third (for 3) of the turn, and the events of a sensor at ``event_scale`` event pixels
per frame pixel over the same time; a classic capture (``discrete_lights=N``) holds N frames under
instantaneous lights spread evenly over one period and no events, or — with ``lights`` ``grid`` or a
light-table file (``pstoolkit.optics.layouts``) — one frame under each light of that layout, cast shadows
swept exactly for every light. Both carry the light model and the ground truth (normal, mask, albedo,
depth in frame pixels, F0, roughness, metallic).

Speed: with the built-in BRDFs on the CPU the compiled engine ``pstoolkit.sim.ring_engine`` renders each
event pixel at its own adaptive times and integrates the frames on the same samples, in parallel
over event pixels (numba); cast shadows are swept every ``SHADOW_STEP_DEG`` of the light's path and
interpolated in between. Other BRDFs (plugins) and other devices take the reference engine:
whole-frame renders on the frames' midpoint-rule samples (``simulate_events(sample_times_us=…)``),
each adding to its frame as it feeds the events, with per-pixel refinement (``render_pixels``).
Both follow the event rule of ``pstoolkit.events.rule``. Memory stays bounded: time is processed in
blocks. An independent renderer (``config.renderer``, the ``renderers`` registry:
``pstoolkit.sim.renderers``) is asked for one image per light of a classic capture, or for key images
every ``key_step_deg`` of a hybrid capture's turn, whose log-linear interpolation gives the frames in
closed form and the events of the reference engine (``pstoolkit.sim.keyed``); the rest of the
assembly (truth, gain, quantisation, light model, calibration) is shared.

Frames: exposure (irradiance × seconds) times a gain that puts the brightest diffuse value of any
frame at ``DIFFUSE_LEVEL`` of the range from black to saturation, so specular highlights may clip as
in an LDR camera (``auto_gain="peak"`` puts the brightest value of all there instead, so nothing
clips, as does a scene with no diffuse part, ``chrome-sphere``); then the frame sensor
(``pstoolkit.sim.sensor.FrameSensor``): black level, optional shot and read noise, quantised to 8, 10,
12 or 16 bits. The same configuration and seed give the same data.

    config = SimulationConfig(scene="blobs", size=128, seed=0)
    summary = simulate(config, "blobs.h5", progress=lambda fraction, message: ...)
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import torch

import psfmt
from pstoolkit._shared.progress import Progress, no_progress
from pstoolkit.errors import UserError
from pstoolkit.events.rule import log_irradiance
from pstoolkit.grid import area_weights, event_shape
from pstoolkit.optics.brdf import GGX
from pstoolkit.optics.grey import GREY_WEIGHTS
from pstoolkit.optics.layouts import layout_light, layout_lights
from pstoolkit.optics.lights import US_PER_S, LightModel, RingLight, SampledLight
from pstoolkit.plugin.manager import get_registries
from pstoolkit.plugin.options import parse_assignments
from pstoolkit.sim import ring_engine
from pstoolkit.sim.config import BIT_DEPTHS, SimulationConfig
from pstoolkit.sim.esim import simulate_events
from pstoolkit.sim.exposure import exposure_plan, exposure_samples
from pstoolkit.sim.keyed import event_render, key_times_us, window_mean
from pstoolkit.sim.render import Renderer
from pstoolkit.sim.renderers import OWN, Rendering
from pstoolkit.sim.ring_kernels.output import window_exposures
from pstoolkit.sim.scenes import SceneMaps
from pstoolkit.sim.sensor import FrameSensor
from pstoolkit.sim.timing import (
    append_event_chunks,
)
from pstoolkit.version import __version__

DIFFUSE_LEVEL = 0.8
DIFFUSE_PERCENTILE = 99.0
"""An independent renderer's automatic gain (``auto_gain="diffuse"``) puts this percentile of the
masked frame values at ``DIFFUSE_LEVEL``: the brightest diffuse value, highlights excluded."""
RENDER_SHARE = 0.8
"""Share of the progress bar given to an independent renderer's key images; the events take the rest."""
# Step of the light (degrees of its path) between the cast-shadow sweeps, interpolated in between
# (``Renderer(shadow_step_us=…)``): one sweep serves all frame and event samples near it.
SHADOW_STEP_DEG = 1.0


@dataclass
class SimulationSummary:
    path: Path
    frames: int
    events: int
    event_size: tuple[int, int] | None
    seconds: float


def build_scene(config: SimulationConfig) -> SceneMaps:
    """The scene's maps at the configured size, from the scene registry."""
    entry = get_registries().scenes.get(config.scene)
    try:
        options = parse_assignments(config.scene_options, entry.options, owner=f"scene {config.scene!r}")
        return entry.obj().build(config.size, config.seed, **options)
    except UserError as exc:
        raise UserError(f"scene {config.scene!r}: {exc}") from None


def build_light(config: SimulationConfig) -> LightModel:
    """The configured ring light, or the lights of a grid or file layout (``SampledLight``)."""
    layout = layout_lights(config.lights)
    if layout is not None:
        return layout_light(*layout)
    return RingLight(elevation_deg=config.elevation_deg, period_us=config.period_us)


def build_renderer(config: SimulationConfig, maps: SceneMaps, brdf: Any) -> Renderer:
    """The scene under the configured ring light, with cast shadows on the simulator's shadow grid, or
    under the lights of a grid or file layout, with cast shadows swept exactly for each of them."""
    light = build_light(config)
    if isinstance(light, SampledLight):
        return Renderer(maps, light, brdf, shadows=config.shadows, device=config.device)
    shadow_step_us = config.period_us / exposure_samples(light, 0, config.period_us, SHADOW_STEP_DEG)
    return Renderer(maps, light, brdf, shadows=config.shadows, device=config.device, shadow_step_us=shadow_step_us)


def prepare_rendering(config: SimulationConfig, maps: SceneMaps) -> Rendering:
    """The scene of ``maps`` made ready by the configured independent renderer (its options parsed)."""
    entry = get_registries().renderers.get(config.renderer)
    options = entry.parse_options(config.renderer_options)
    try:
        return entry.obj().prepare(maps, config.seed, **options)
    except UserError as exc:
        raise UserError(f"renderer {config.renderer!r}: {exc}") from None


def compiled_blocks(config: SimulationConfig, renderer: Renderer) -> Iterator[ring_engine.Block]:
    """``pstoolkit.sim.ring_engine.simulate_ring`` over all periods of ``config``, with the first period's windows."""
    return ring_engine.simulate_ring(
        renderer,
        event_scale=config.event_scale,
        t1_us=config.duration_us,
        window_ends_us=config.exposure_bounds_us()[1:],
        sensor=config.sensor(),
        min_dt_us=config.min_step_us,
    )


def _auto_gain(peak: float, sensor: FrameSensor, overall_peak: float = 0.0) -> float:
    """The gain that puts ``peak`` (the brightest value the gain is set by) at ``DIFFUSE_LEVEL`` of the
    sensor's range above black; a scene with no diffuse part (``peak`` 0: a chrome sphere) is set by
    ``overall_peak`` instead."""
    peak = peak if peak > 0 else overall_peak
    if not peak > 0:
        raise UserError("the scene receives no light (every frame is black); check --elevation-deg or --lights")
    return DIFFUSE_LEVEL * sensor.signal_range() / peak


def _gain_brdfs(config: SimulationConfig, renderer: Renderer, diffuse: Any) -> list[Any]:
    """The BRDFs the frames are shaded with: the renderer's, then the diffuse one when the automatic
    gain is set by the diffuse part; the gain is set by the last one's values."""
    fixed = config.exposure_gain is not None or config.auto_gain == "peak"
    return [renderer.brdf] if fixed else [renderer.brdf, diffuse]


def _description(config: SimulationConfig) -> str:
    return f"pstoolkit simulate {config.scene}: " + json.dumps(asdict(config), sort_keys=True)


def simulate(config: SimulationConfig, path: str | os.PathLike[str], progress: Progress = no_progress) -> SimulationSummary:
    """Render ``config`` and write the capture to ``path`` atomically; ``progress(fraction, message)``
    is called as work advances. ``config.device`` is a torch device ("cpu", "cuda").

    On the CPU torch runs single-threaded here: the reference engine's render steps are many small
    tensor operations, where handing work between threads costs more than it saves
    (``docs/simulator-tuning.md``); the compiled engine runs on numba's threads (``NUMBA_NUM_THREADS``)."""
    threads = torch.get_num_threads()
    if torch.device(config.device).type == "cpu":
        torch.set_num_threads(1)
    try:
        return _simulate(config, path, progress)
    finally:
        torch.set_num_threads(threads)


def _simulate(config: SimulationConfig, path: str | os.PathLike[str], progress: Progress) -> SimulationSummary:
    started = time.perf_counter()
    config.check()
    report = progress
    path = Path(path)
    if not path.parent.is_dir():
        raise UserError(f"{path}: folder {path.parent} does not exist")
    registries = get_registries()
    maps = build_scene(config)
    rendering = None if config.renderer == OWN else prepare_rendering(config, maps)
    noise_rng, _ = (np.random.default_rng(s) for s in np.random.SeedSequence(config.seed).spawn(2))
    n_events = 0
    event_size: tuple[int, int] | None = None
    # what an independent renderer draws is the truth: its mask of wholly covered pixels and its normals
    normal, mask = (maps.normal, maps.mask) if rendering is None else (rendering.normal, rendering.mask)
    with psfmt.CaptureWriter(
        path, description=_description(config), creator="pstoolkit", creator_version=__version__
    ) as writer:
        # first, so the writer's threads compress the maps while the engine is set up
        writer.set_ground_truth(
            psfmt.GroundTruth(normal=normal, mask=mask, albedo=maps.albedo, depth=maps.depth, materials=maps.materials())
        )
        sensor = config.frame_sensor()
        writer.begin_frames(config.size, config.size, 3, BIT_DEPTHS[sensor.bit_depth], bit_depth=sensor.bit_depth,
                            black_level=sensor.black_level)
        if rendering is not None:
            light = build_light(config)
            if config.discrete:
                n_frames = _write_rendered_discrete(config, rendering, light, writer, noise_rng, report)
            else:
                n_events, event_size = _write_rendered_hybrid(config, rendering, light, writer, noise_rng, report)
        else:
            renderer = build_renderer(config, maps, registries.brdfs.get(config.brdf).obj())
            light = renderer.light
            diffuse = registries.brdfs.get("lambertian").obj()
            if config.discrete:
                n_frames = _write_discrete(config, renderer, diffuse, writer, noise_rng, report)
            else:
                n_events, event_size = _write_hybrid(config, renderer, diffuse, writer, noise_rng, report)
        if not config.discrete:
            n_frames = config.frames * config.periods
            writer.set_calibration(config.calibration())
        writer.set_lights(light.to_spec())
    return SimulationSummary(path, n_frames, n_events, event_size, time.perf_counter() - started)


class _FrameSums:
    """The long exposures of one period, ∫ I dt by ``exposure_plan``'s midpoint rule, on the time grid
    the event simulation renders whole frames at (``sample_times_us``): each such render also adds
    its time's irradiance to its frame (``render``), so one period is shaded once for both, and the
    cast-shadow sweeps cached for one time serve its neighbours. The light repeats every period, so
    the frames of the first period are reused for the others."""

    def __init__(self, config: SimulationConfig, renderer: Renderer, brdfs: list[Any], bounds: list[int]) -> None:
        self.bounds = bounds
        plans = [exposure_plan(renderer.light, a, b) for a, b in zip(self.bounds[:-1], self.bounds[1:])]
        self.times = np.concatenate([times for times, _ in plans])
        self.window = np.repeat(np.arange(config.frames), [len(times) for times, _ in plans])
        self.dt_s = [dt_s for _, dt_s in plans]
        self.done = np.zeros(len(self.times), dtype=bool)
        self.totals = [[torch.zeros((renderer.pixels, 3), dtype=torch.float64) for _ in brdfs] for _ in plans]
        self.renderer, self.brdfs, self.config = renderer, brdfs, config

    def sample_times_us(self) -> np.ndarray:
        """The frame samples of every period, inside (0, periods × period)."""
        period = self.config.period_us
        times = np.concatenate([self.times + p * period for p in range(self.config.periods)])
        return times[(times > 0) & (times < self.config.duration_us)]

    def _add(self, index: np.ndarray, sums: list[torch.Tensor]) -> None:
        for total, part in zip(self.totals[int(self.window[index[0]])], sums):
            total += part.cpu()
        self.done[index] = True

    def render(self, t_us: np.ndarray, event_scale: float) -> np.ndarray:
        """``event_grey`` at ``t_us``; the frame samples among them not seen before join their frame."""
        t_us = np.asarray(t_us, dtype=np.float64)
        slot = np.minimum(np.searchsorted(self.times, t_us), len(self.times) - 1)
        new = (self.times[slot] == t_us) & ~self.done[slot]
        if not new.any():
            return self.renderer.event_grey(t_us, event_scale)
        he, we = event_shape(self.config.size, self.config.size, event_scale)
        out = np.empty((len(t_us), he, we))
        if not new.all():
            out[~new] = self.renderer.event_grey(t_us[~new], event_scale)
        for k in np.unique(self.window[slot[new]]):
            take = new & (self.window[slot] == k)
            out[take], sums = self.renderer.event_grey_and_sums(t_us[take], event_scale, self.brdfs)
            self._add(slot[take], sums)
        return out

    def exposures(self) -> list[list[np.ndarray]]:
        """Per frame, (H, W, 3) radiant exposure per BRDF (dt in seconds); samples the event
        simulation did not render are shaded here."""
        for k in np.unique(self.window[~self.done]):
            index = np.flatnonzero(~self.done & (self.window == k))
            self._add(index, self.renderer.shade_sum(self.times[index], self.brdfs))
        return [
            [self.renderer.scatter(total[None].to(self.renderer.device) * dt_s)[0].cpu().numpy() for total in totals]
            for totals, dt_s in zip(self.totals, self.dt_s)
        ]


def _write_hybrid(
    config: SimulationConfig,
    renderer: Renderer,
    diffuse: Any,
    writer: psfmt.CaptureWriter,
    rng: np.random.Generator,
    report: Progress,
) -> tuple[int, tuple[int, int]]:
    """Events and long exposures tiling each period, in one pass over time."""
    brdfs = _gain_brdfs(config, renderer, diffuse)
    event_size = event_shape(config.size, config.size, config.event_scale)
    bounds = config.exposure_bounds_us()
    if ring_engine.supported(renderer):
        n_events, exposures = _write_compiled(config, renderer, event_size, writer, report, brdfs)
    else:
        sums = _FrameSums(config, renderer, brdfs, bounds)
        n_events = _write_events(config, renderer, event_size, writer, report, sums)
        exposures = sums.exposures()
    gain = config.exposure_gain or _auto_gain(
        max(float(e[-1].max()) for e in exposures), config.frame_sensor(), max(float(e[0].max()) for e in exposures)
    )
    _append_windows(config, [e[0] for e in exposures], gain, writer, rng)
    return n_events, event_size


def _append_windows(
    config: SimulationConfig, exposures: list[np.ndarray], gain: float, writer: psfmt.CaptureWriter, rng: np.random.Generator
) -> None:
    """The long exposures (H, W, 3) of the first period's windows as frames of every period, through
    the frame sensor."""
    sensor = config.frame_sensor()
    period = config.period_us
    bounds = config.exposure_bounds_us()
    for p in range(config.periods):
        for k, exposure in enumerate(exposures):
            writer.append_frames(
                sensor.quantise(gain * exposure, rng),
                t_start_us=[p * period + bounds[k]],
                t_end_us=[p * period + bounds[k + 1]],
            )


def _write_compiled(
    config: SimulationConfig,
    renderer: Renderer,
    event_size: tuple[int, int],
    writer: psfmt.CaptureWriter,
    report: Progress,
    brdfs: list[Any],
) -> tuple[int, list[list[np.ndarray]]]:
    """Events over all periods and the first period's exposures per BRDF, from ``ring_engine``."""
    window_sums = []

    def chunks() -> Iterator[tuple[psfmt.EventArray, float]]:
        for block in compiled_blocks(config, renderer):
            if block.window_sums is not None:
                window_sums.append(block.window_sums)
            yield block.events, block.t_end_us

    count = append_event_chunks(writer, event_size, chunks(), config.duration_us, report)
    exposures = []
    for sums in window_sums:
        diffuse, gloss = window_exposures(ring_engine.shaded_scene(renderer), sums)
        exposures.append([gloss if isinstance(b, GGX) else diffuse for b in brdfs])
    return count, exposures


def _discrete_times(config: SimulationConfig, light: LightModel) -> np.ndarray:
    """The times of a classic capture's lights: each light of a grid or file layout (at its sample
    time), or ``discrete_lights`` times evenly spaced over the first period of the ring."""
    if isinstance(light, SampledLight):
        return light.times_us
    return np.arange(config.discrete_lights, dtype=np.float64) * config.period_us / config.discrete_lights


def _write_discrete(
    config: SimulationConfig,
    renderer: Renderer,
    diffuse: Any,
    writer: psfmt.CaptureWriter,
    rng: np.random.Generator,
    report: Progress,
) -> int:
    """One frame per instantaneous light: each light of a grid or file layout (at its sample time),
    or ``discrete_lights`` ring lights evenly spaced over the first period. Returns the frame count."""
    t_us = _discrete_times(config, renderer.light)
    shaded = renderer.shade(t_us, _gain_brdfs(config, renderer, diffuse))
    images = renderer.scatter(shaded[0]).cpu().numpy()
    report(1.0, "frames")
    sensor = config.frame_sensor()
    gain = config.exposure_gain or _auto_gain(float(shaded[-1].max()), sensor, float(shaded[0].max()))
    direction, intensity = renderer.light.evaluate(t_us)
    writer.append_frames(
        sensor.quantise(gain * images, rng),
        light_direction=direction,
        light_intensity=intensity,
    )
    return len(t_us)


def _write_events(
    config: SimulationConfig,
    renderer: Renderer,
    event_size: tuple[int, int],
    writer: psfmt.CaptureWriter,
    report: Progress,
    sums: _FrameSums,
) -> int:
    """Events over all periods; their whole-frame renders go through ``sums``, which adds the
    frames' samples among them to the exposures."""
    height, width = event_size
    scale = config.event_scale
    render_pixels = partial(renderer.event_pixels, event_scale=scale) if renderer.event_pixels_supported else None
    chunks = simulate_events(
        partial(sums.render, event_scale=scale),
        0,
        config.duration_us,
        width=width,
        height=height,
        sensor=config.sensor(),
        min_dt_us=config.min_step_us,
        render_pixels=render_pixels,
        sample_times_us=sums.sample_times_us(),
    )
    return append_event_chunks(writer, event_size, ((c, float(c.t[-1])) for c in chunks), config.duration_us, report)




def _rendered_gain(config: SimulationConfig, values: np.ndarray, mask: np.ndarray) -> float:
    """The gain of an independent renderer's frames (``values`` (N, H, W, 3)): ``--exposure-gain``, or
    the automatic gain set by the brightest value (``peak``) or, as the renderer cannot tell the
    diffuse part apart, by the ``DIFFUSE_PERCENTILE``-th percentile of the masked values."""
    if config.exposure_gain is not None:
        return config.exposure_gain
    inside = values[:, mask] if mask.any() else values
    peak = float(inside.max()) if config.auto_gain == "peak" else float(np.percentile(inside, DIFFUSE_PERCENTILE))
    return _auto_gain(peak, config.frame_sensor())


def _write_rendered_discrete(
    config: SimulationConfig, rendering: Rendering, light: LightModel, writer: psfmt.CaptureWriter,
    rng: np.random.Generator, report: Progress,
) -> int:
    """A classic capture of an independent renderer: one rendered frame per instantaneous light.
    Returns the frame count."""
    t_us = _discrete_times(config, light)
    images = rendering.images(light, t_us, report)
    gain = _rendered_gain(config, images, rendering.mask)
    direction, intensity = light.evaluate(t_us)
    writer.append_frames(
        config.frame_sensor().quantise(gain * images, rng), light_direction=direction, light_intensity=intensity
    )
    return len(t_us)


def _write_rendered_hybrid(
    config: SimulationConfig, rendering: Rendering, light: LightModel, writer: psfmt.CaptureWriter,
    rng: np.random.Generator, report: Progress,
) -> tuple[int, tuple[int, int]]:
    """A hybrid capture of an independent renderer: key images every ``key_step_deg`` of the first
    turn, then the long exposures in closed form and the events of ESIM over the log-linear
    interpolation between keys (``pstoolkit.sim.keyed``), periodic over all periods."""
    period = config.period_us
    knots = key_times_us(period, int(np.ceil(360.0 / config.key_step_deg - 1e-9)))
    images = rendering.images(light, knots[:-1].astype(np.float64), lambda f, m: report(RENDER_SHARE * f, m))
    log_rgb = log_irradiance(images.astype(np.float64))
    bounds = config.exposure_bounds_us()
    exposures = [
        window_mean(log_rgb, knots, bounds[k], bounds[k + 1]) * ((bounds[k + 1] - bounds[k]) / US_PER_S)
        for k in range(config.frames)
    ]
    _append_windows(config, exposures, _rendered_gain(config, np.stack(exposures), rendering.mask), writer, rng)
    del log_rgb
    height, width = event_shape(config.size, config.size, config.event_scale)
    av = area_weights(height, config.size, config.event_scale)
    au = area_weights(width, config.size, config.event_scale)
    grey = images.astype(np.float64) @ np.asarray(GREY_WEIGHTS)
    log_keys = log_irradiance(av @ grey @ au.T)
    chunks = simulate_events(
        event_render(log_keys, knots, period), 0, config.duration_us, width=width, height=height,
        sensor=config.sensor(), min_dt_us=config.min_step_us,
    )
    count = append_event_chunks(
        writer, (height, width), ((c, float(c.t[-1])) for c in chunks), config.duration_us,
        lambda f, m: report(RENDER_SHARE + (1.0 - RENDER_SHARE) * f, m),
    )
    return count, (height, width)
