"""Independent renderers of the simulator (the ``renderers`` registry): a plugin's renderer draws a
scene's images under any light at given times, and the simulator turns them into a capture.

    entry = get_registries().renderers.get("mitsuba")
    rendering = entry.obj().prepare(maps, seed=0, **entry.parse_options(["spp=16"]))
    images = rendering.images(light, t_us)       # (T, H, W, 3) float32 linear irradiance

The simulator's own engines (``--renderer own``, the default) are not in this registry: they render
the built-in BRDFs in closed form at every time the event simulation asks for. An independent
renderer is asked for key images only: every ``key_step_deg`` of the light's turn for a hybrid
capture (``pstoolkit.sim.keyed``), or one image per instantaneous light for a classic capture.

Scale: a Lambertian surface of albedo ρ facing a directional light of intensity e must come out as
ρ·e·cos θ, the scale of the built-in renderer (``pstoolkit.sim.render``), so that the event sensor's
ε and the automatic gain mean the same for every renderer.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any, ClassVar

import numpy as np

from pstoolkit._shared.progress import Progress, no_progress
from pstoolkit.optics.lights import LightModel
from pstoolkit.plugin.options import Option
from pstoolkit.sim.scenes import SceneMaps

OWN = "own"
"""``--renderer`` value of the simulator's built-in engines."""


class Rendering(ABC):
    """One scene made ready by a renderer (geometry loaded, materials bound): its images under any
    light, and what it renders as ground truth.

    ``mask`` (H, W) bool marks the pixels the rendered surface covers wholly; ``normal`` (H, W, 3)
    float32 are their unit normals in the camera frame (x right, y up, z towards the camera), 0
    outside the mask."""

    mask: np.ndarray
    normal: np.ndarray

    @abstractmethod
    def images(self, light: LightModel, t_us: np.ndarray, progress: Progress = no_progress) -> np.ndarray:
        """(T, H, W, 3) float32 linear RGB irradiance (≥ 0, the scale of the module docstring) of the
        scene under ``light`` at the times ``t_us`` (T,), µs; ``progress(fraction, message)`` as the
        images are drawn."""


class SceneRenderer(ABC):
    """An independent renderer of the ``renderers`` registry. Subclasses set ``name``, ``summary``
    and typed ``options`` and make a scene ready (``prepare``)."""

    name: ClassVar[str]
    summary: ClassVar[str]
    options: ClassVar[tuple[Option, ...]] = ()

    @abstractmethod
    def prepare(self, maps: SceneMaps, seed: int, **options: Any) -> Rendering:
        """The scene of ``maps`` (its geometry, albedo, F0, roughness and metallic maps) ready to
        render; ``seed`` draws every random choice of the renderer (its sample patterns),
        ``options`` are the entry's options by name (defaults filled in). UserError for an option
        the renderer cannot honour."""
