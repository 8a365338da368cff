"""One call from a scene to path-traced data: a hybrid capture, a DiLiGenT object folder, or both.

    render_scene("blobs", size=128, bsdf="roughplastic", seed=0, capture=Path("blobs-pt.h5"))
    render_scene(Path("bearPNG-geometry"), bsdf="roughconductor", diligent=Path("bearPT"))

The capture is ``pstoolkit simulate SCENE --renderer mitsuba``; the folder is the classic capture of
DiLiGenT's 96 grid lights (``--lights grid --bit-depth 16 --auto-gain peak``) exported as
``pstoolkit export --frames diligent`` does, so ``pstoolkit convert diligent FOLDER --semi-real``
reads it as it reads a real object.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import replace
from pathlib import Path
from typing import Any

from pstoolkit import Progress, UserError, no_progress
from pstoolkit.io.diligent_export import export_diligent
from pstoolkit.optics.layouts import GRID
from pstoolkit.sim.config import SimulationConfig
from pstoolkit.sim.simulator import SimulationSummary, simulate

RENDERER = "mitsuba"
GEOMETRY = "geometry"
RENDER_OPTIONS = ("bsdf", "conductor", "spp", "max_depth", "variant")


def scene_config(scene: str | os.PathLike[str], *, size: int = 128, seed: int = 0, bsdf: str = "roughplastic",
                 scene_options: dict[str, Any] | None = None, **settings: Any) -> SimulationConfig:
    """The ``SimulationConfig`` of a path-traced capture of ``scene``: a registered scene's name, or a
    geometry folder (``normal_map.png``, ``depth_gt.npz``, ``mask.png``, ``K.txt``: the ``geometry``
    scene). ``scene_options`` are the scene's options by name; ``settings`` are the renderer's
    (``conductor``, ``spp``, ``max_depth``, ``variant``) and any other ``SimulationConfig`` field
    (``event_scale``, ``frames``, ``contrast``, ``refractory_us``, ``key_step_deg``, …)."""
    options = dict(scene_options or {})
    name = str(scene)
    if isinstance(scene, os.PathLike) or os.sep in name or Path(name).is_dir():
        options["source"] = str(scene)
        name = GEOMETRY
    render = {"bsdf": bsdf, **{k: settings.pop(k) for k in list(settings) if k in RENDER_OPTIONS}}
    try:
        return SimulationConfig(
            scene=name, size=size, seed=seed, renderer=RENDERER,
            scene_options=[f"{k}={v}" for k, v in options.items()],
            renderer_options=[f"{k}={v}" for k, v in render.items()], **settings,
        )
    except TypeError as exc:
        raise UserError(f"render_scene: {exc}") from None


def render_scene(scene: str | os.PathLike[str], *, capture: os.PathLike[str] | None = None,
                 diligent: os.PathLike[str] | None = None, force: bool = False, progress: Progress = no_progress,
                 **settings: Any) -> dict[str, Any]:
    """Path-trace ``scene`` (see ``scene_config`` for it and ``settings``: ``size``, ``seed``,
    ``bsdf``, ``scene_options``, renderer and capture options) into a hybrid capture at ``capture``
    and/or a DiLiGenT object folder at ``diligent`` (an existing non-empty folder needs ``force``).

    Returns ``{"capture": SimulationSummary | None, "diligent": ExportedFolder | None}``. UserError
    for a bad option, a missing folder, or neither output asked for."""
    if capture is None and diligent is None:
        raise UserError("render_scene: give capture=PATH, diligent=FOLDER or both")
    config = scene_config(scene, **settings)
    written: dict[str, Any] = {"capture": None, "diligent": None}
    if capture is not None:
        written["capture"] = simulate(config, capture, progress)
    if diligent is not None:
        written["diligent"] = write_diligent(config, Path(diligent), force=force, progress=progress)
    return written


def write_diligent(config: SimulationConfig, folder: Path, *, force: bool = False, progress: Progress = no_progress) -> Any:
    """The DiLiGenT object folder of ``config``'s scene under the 96 grid lights (16-bit, gain by the
    brightest value so nothing clips), through a classic capture kept beside ``folder`` until the
    folder is written. Returns the ``ExportedFolder``."""
    grid = replace(config, lights=GRID, discrete_lights=0, bit_depth=16, auto_gain="peak", noise=0.0)
    if not folder.parent.is_dir():
        raise UserError(f"{folder}: folder {folder.parent} does not exist")
    with tempfile.TemporaryDirectory(dir=folder.parent, prefix=f".{folder.name}.") as staging:
        classic = Path(staging) / "grid.h5"
        summary: SimulationSummary = simulate(grid, classic, lambda f, m: progress(0.9 * f, m))
        del summary
        return export_diligent(classic, folder, force=force, progress=lambda f, m: progress(0.9 + 0.1 * f, m))
