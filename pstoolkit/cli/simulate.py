"""``pstoolkit simulate SCENE -o OUT.h5``: render a registered scene into a hybrid (or classic) capture."""

from __future__ import annotations

import json
from pathlib import Path

import typer

from pstoolkit.cli.app import app, echo, progress_bar
from pstoolkit.errors import UserError
from pstoolkit.plugin.manager import get_registries
from pstoolkit.sim.config import SimulationConfig
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
    contrast: float = typer.Option(_DEFAULTS.contrast, "--contrast", help="Event contrast threshold C (log units, both polarities)."),
    contrast_sigma: float = typer.Option(_DEFAULTS.contrast_sigma, "--contrast-sigma", help="Per-pixel spread of the contrast threshold."),
    refractory_us: float = typer.Option(_DEFAULTS.refractory_us, "--refractory-us", help="Event refractory period, µs."),
    refractory_rule: str = typer.Option(_DEFAULTS.refractory_rule, "--refractory-rule", help=(
        "What an event pixel does after its refractory period: reset-at-end (its reference resets to the level it sees "
        "then) or rate-limited (the reference moves one threshold per event; a change that persists keeps firing every "
        "refractory period). See docs/sensors.md."
    )),
    noise: float = typer.Option(_DEFAULTS.noise, "--noise", help=(
        "Frame read noise as a fraction of saturation, with shot noise of a 1/noise² e⁻ full well (0: none)."
    )),
    brdf: str = typer.Option(_DEFAULTS.brdf, "--brdf", help="A registered BRDF: lambertian, ggx or a plugin's."),
    bit_depth: int = typer.Option(_DEFAULTS.bit_depth, "--bit-depth", help="Frame bits: 8 (uint8), 12 or 16 (uint16)."),
    exposure_gain: float | None = typer.Option(None, "--exposure-gain", help="Pixel units per irradiance·second (default: set by --auto-gain)."),
    auto_gain: str = typer.Option(_DEFAULTS.auto_gain, "--auto-gain", help=(
        "The automatic gain puts at 80 % of saturation: diffuse, the brightest diffuse value of any frame (specular "
        "highlights may clip, as in an LDR camera), or peak, the brightest value of all (nothing clips: for 16-bit "
        "renders of shiny materials)."
    )),
    shadows: bool = typer.Option(True, "--shadows/--no-shadows", help="Render cast shadows."),
    source: Path | None = typer.Option(None, "--source", help="Folder of the geometry scene (normal_map.png, depth_gt.npz, mask.png, K.txt)."),
    assignments: list[str] = typer.Option([], "--set", metavar="KEY=VALUE", help="A scene option (see `pstoolkit plugins`); repeat for more."),
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
    scene_options = list(assignments)
    if source is not None:
        if not any(o.name == "source" for o in entry.options):
            raise UserError(f"--source: scene {scene!r} takes no source folder")
        scene_options.append(f"source={source}")
    config = SimulationConfig(
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
        contrast=contrast,
        contrast_sigma=contrast_sigma,
        refractory_us=refractory_us,
        refractory_rule=refractory_rule,
        noise=noise,
        brdf=brdf,
        bit_depth=bit_depth,
        exposure_gain=exposure_gain,
        auto_gain=auto_gain,
        shadows=shadows,
        device=resolve_device(device),
    )
    from pstoolkit.sim.simulator import simulate  # deferred: the simulator loads torch and numba

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
