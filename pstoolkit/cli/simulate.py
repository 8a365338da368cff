"""``pstoolkit simulate SCENE -o OUT.h5``: render a registered scene into a hybrid (or classic) capture."""

from __future__ import annotations

import json
from pathlib import Path

import typer

from psfmt.atomic import check_target
from pstoolkit.cli.app import app, echo, progress_bar
from pstoolkit.errors import UserError
from pstoolkit.plugin.manager import get_registries
from pstoolkit.sim.config import SimulationConfig
from pstoolkit.sim.renderers import OWN
from pstoolkit.sim.sensor import SENSOR_PRESETS
from pstoolkit.solve.base import resolve_device

_DEFAULTS = SimulationConfig()


@app.command("simulate")
def simulate_command(
    scene: str = typer.Argument(..., help="A registered scene: sphere, chrome-sphere, blobs, relief, geometry or a plugin's."),
    out: Path = typer.Option(..., "-o", "--out", help="The capture file to write (HDF5)."),
    size: int = typer.Option(_DEFAULTS.size, "--size", help="Frame width and height in pixels."),
    seed: int = typer.Option(_DEFAULTS.seed, "--seed", help="Seed of every random choice; the same seed writes the same data."),
    event_scale: float = typer.Option(_DEFAULTS.event_scale, "--event-scale", help="Event pixels per frame pixel (0.5: half the resolution per axis)."),
    frames: int = typer.Option(_DEFAULTS.frames, "--frames", help="Long-exposure frames per light period."),
    discrete_lights: int = typer.Option(0, "--discrete-lights", help=(
        "Write a classic capture: N instantaneous lights on the same trajectory, one frame each, no events (with "
        "--lights grid|FILE: its K lights, N = K or 0)."
    )),
    lights: str = typer.Option(_DEFAULTS.lights, "--lights", help=(
        "Lights of a classic capture: ring (N lights over one turn of the ring), grid (DiLiGenT's 12×8 grid, 96 lights,"
        " id = 8·column + row) or a light_directions.txt FILE (K lines x y z, with the light_intensities.txt beside it,"
        " RGB, when present). grid and FILE always write a classic capture."
    )),
    periods: int = typer.Option(_DEFAULTS.periods, "--periods", help="Light periods to record."),
    period_ms: float = typer.Option(_DEFAULTS.period_ms, "--period-ms", help="One turn of the ring light, milliseconds."),
    elevation_deg: float = typer.Option(_DEFAULTS.elevation_deg, "--elevation-deg", help="Elevation of the ring light above the image plane, degrees."),
    sensor: str = typer.Option(_DEFAULTS.sensor_model, "--sensor", help=(
        f"Sensor preset, event and frame sensor: {', '.join(SENSOR_PRESETS)} (docs/sensors.md). The sensor options below "
        "override single fields of it; their defaults are the preset's (those of ideal shown)."
    )),
    contrast: float | None = typer.Option(None, "--contrast", help=f"Event contrast threshold C, both polarities (log units) [ideal: {_DEFAULTS.contrast:g}]."),
    contrast_pos: float | None = typer.Option(None, "--contrast-pos", help="Threshold C⁺ of +1 events (log units)."),
    contrast_neg: float | None = typer.Option(None, "--contrast-neg", help="Threshold C⁻ of −1 events (log units)."),
    contrast_sigma: float | None = typer.Option(None, "--contrast-sigma", help="Per-pixel spread σ of the thresholds, each N(C, σ) [ideal: 0]."),
    refractory_us: float | None = typer.Option(None, "--refractory-us", help=f"Event refractory period, µs [ideal: {_DEFAULTS.refractory_us:g}]."),
    refractory_rule: str | None = typer.Option(None, "--refractory-rule", help=(
        "What an event pixel does after its refractory period: reset-at-end (its reference resets to the level it sees "
        "then) or rate-limited (the reference moves one threshold per event; a change that persists keeps firing every "
        f"refractory period). See docs/sensors.md [ideal: {_DEFAULTS.refractory_rule}]."
    )),
    leak_hz: float | None = typer.Option(None, "--leak-hz", help="Leak (background activity): +1 events per pixel and second of a static pixel [ideal: 0]."),
    shot_noise_hz: float | None = typer.Option(None, "--shot-noise-hz", help=(
        "Shot-noise events per pixel and second in the dark, ±1; a quarter of it at irradiance 1 [ideal: 0]."
    )),
    rate_spread_decades: float | None = typer.Option(None, "--rate-spread-decades", help=(
        "Per-pixel spread of the leak and shot rates, decades (log10 σ) [ideal: 0]."
    )),
    hot_pixel_fraction: float | None = typer.Option(None, "--hot-pixel-fraction", help="Share of hot pixels [ideal: 0]."),
    hot_pixel_hz: float | None = typer.Option(None, "--hot-pixel-hz", help="Events per second of a hot pixel, ±1 [ideal: 0]."),
    bit_depth: int | None = typer.Option(None, "--bit-depth", help="Frame bits: 8 (uint8), 10, 12 or 16 (uint16) [ideal: 8]."),
    black_level: float | None = typer.Option(None, "--black-level", help="Stored frame value of no light [ideal: 0]."),
    full_well_e: float | None = typer.Option(None, "--full-well-e", help="Frame pixel's electrons at saturation: photon shot noise (0: none) [ideal: 0]."),
    read_noise_e: float | None = typer.Option(None, "--read-noise-e", help="Frame read noise, electrons rms (needs a full well) [ideal: 0]."),
    noise: float = typer.Option(_DEFAULTS.noise, "--noise", help=(
        "Frame noise in one number: read noise of this fraction of saturation with the shot noise of a 1/noise² e⁻ "
        "full well, over --full-well-e and --read-noise-e (0: those)."
    )),
    brdf: str = typer.Option(_DEFAULTS.brdf, "--brdf", help="A registered BRDF: lambertian, ggx or a plugin's."),
    exposure_gain: float | None = typer.Option(None, "--exposure-gain", help="Pixel units per irradiance·second (default: set by --auto-gain)."),
    auto_gain: str = typer.Option(_DEFAULTS.auto_gain, "--auto-gain", help=(
        "The automatic gain puts at 80 % of saturation: diffuse, the brightest diffuse value of any frame (specular "
        "highlights may clip, as in an LDR camera), or peak, the brightest value of all (nothing clips: for 16-bit "
        "renders of shiny materials)."
    )),
    shadows: bool = typer.Option(True, "--shadows/--no-shadows", help="Render cast shadows."),
    source: Path | None = typer.Option(None, "--source", help=(
        "Folder of the geometry scene (normal_map.png, depth_gt.npz, mask.png, K.txt), or file of the mesh scene (mitsuba plugin)."
    )),
    assignments: list[str] = typer.Option([], "--set", metavar="KEY=VALUE", help="A scene option (see `pstoolkit plugins`); repeat for more."),
    renderer: str = typer.Option(_DEFAULTS.renderer, "--renderer", help=(
        "own (the built-in engines: --brdf, --shadows, --device) or an independent renderer of a plugin (mitsuba: path "
        "traced, pip install 'pstoolkit[mitsuba]'; docs/renderers.md)."
    )),
    render_assignments: list[str] = typer.Option([], "--render-set", metavar="KEY=VALUE", help=(
        "An option of the --renderer (mitsuba: bsdf, spp, max_depth, variant; see `pstoolkit plugins`); repeat for more."
    )),
    key_step_deg: float = typer.Option(_DEFAULTS.key_step_deg, "--key-step-deg", help=(
        "An independent renderer's hybrid capture: degrees of the turn between key images, log-linearly interpolated in between."
    )),
    device: str = typer.Option("auto", "--device", help=(
        "auto (CUDA when available, else cpu), cpu or cuda. On cpu the ggx and lambertian BRDFs render with the compiled "
        "engine and plugin BRDFs with torch; on cuda everything renders with torch."
    )),
    as_json: bool = typer.Option(False, "--json", help="Print what was written as JSON (file, frames, events, seconds) and no progress."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar and no summary line."),
) -> None:
    """Render SCENE under a ring light and write a capture with ground truth: long-exposure frames and
    events (default), or a classic capture of N instantaneous lights (--discrete-lights N), or of the
    lights of DiLiGenT's grid or a light-table file (--lights grid|FILE)."""
    entry = get_registries().scenes.get(scene)
    if renderer != OWN:
        get_registries().renderers.get(renderer)
    scene_options = list(assignments)
    if source is not None:
        if not any(o.name == "source" for o in entry.options):
            raise UserError(f"--source: scene {scene!r} takes no source folder")
        scene_options.append(f"source={source}")
    if contrast is not None:
        contrast_pos = contrast if contrast_pos is None else contrast_pos
        contrast_neg = contrast if contrast_neg is None else contrast_neg
    config = SimulationConfig.with_preset(
        sensor,
        scene=scene,
        size=size,
        seed=seed,
        scene_options=scene_options,
        event_scale=event_scale,
        frames=frames,
        discrete_lights=discrete_lights,
        lights=lights,
        periods=periods,
        period_ms=period_ms,
        elevation_deg=elevation_deg,
        contrast=contrast_pos,
        contrast_neg=contrast_neg,
        contrast_sigma=contrast_sigma,
        refractory_us=refractory_us,
        refractory_rule=refractory_rule,
        leak_hz=leak_hz,
        shot_noise_hz=shot_noise_hz,
        rate_spread_decades=rate_spread_decades,
        hot_pixel_fraction=hot_pixel_fraction,
        hot_pixel_hz=hot_pixel_hz,
        bit_depth=bit_depth,
        black_level=black_level,
        full_well_e=full_well_e,
        read_noise_e=read_noise_e,
        noise=noise,
        brdf=brdf,
        exposure_gain=exposure_gain,
        auto_gain=auto_gain,
        shadows=shadows,
        device=resolve_device(device),
        renderer=renderer,
        renderer_options=list(render_assignments),
        key_step_deg=key_step_deg,
    )
    from pstoolkit.sim.simulator import simulate  # deferred: the simulator loads torch and numba

    check_target(out, [Path(lights)] if lights not in ("ring", "grid") else [])  # before a long render

    progress = progress_bar(f"simulate {scene}", quiet or as_json)
    summary = simulate(config, out, progress)
    if as_json:
        event_grid = summary.event_size
        echo(json.dumps({
            "file": str(summary.path),
            "frames": {"count": summary.frames, "width": size, "height": size},
            "events": None if event_grid is None else {"count": summary.events, "width": event_grid[1], "height": event_grid[0]},
            "seconds": summary.seconds,
        }, indent=2))
        return
    if quiet:
        return
    events = (
        f", {summary.events:,} events at {summary.event_size[1]}×{summary.event_size[0]}"
        if summary.event_size is not None
        else ""
    )
    echo(f"wrote {summary.path}: {summary.frames} frames at {size}×{size}{events}, {summary.seconds:.1f} s")
