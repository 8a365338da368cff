"""The ``mitsuba`` renderer: a scene's height field path-traced by Mitsuba 3.

The scene's depth and normals become a triangle mesh (``pstoolkit_mitsuba.heightfield``, shading
normals the scene's), its materials a Mitsuba BSDF with the albedo map as texture
(``pstoolkit_mitsuba.materials``); an orthographic camera looks down −z, one frame pixel per pixel
(the simulator's projection), with a box filter, so a pixel is the mean radiance over its footprint.
Each light is a Mitsuba emitter — a directional one for a far light, a point light for a near one
(``position_mm``, ``pixel_pitch_mm``: ``NearRingLight``) — and the path tracer adds what the
built-in renderer lacks: light reflected from other parts of the surface, up to ``max_depth``
segments of a path (2: direct light only; 3: one bounce of inter-reflection; …).

Scale: radiance × π, so a Lambertian surface of albedo ρ under a directional light of intensity e
renders as ρ·e·cos θ, the built-in renderer's scale (``pstoolkit.sim.renderers``).

Every image is drawn with the same sample pattern (Mitsuba's ``seed``, from the capture's seed):
between two nearby lights the Monte-Carlo noise then changes little, so the events of the key
images' interpolation come from the light's motion rather than from the noise.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import numpy as np

from pstoolkit import LightModel, Option, Progress, UserError, no_progress
from pstoolkit.sim.renderers import Rendering, SceneRenderer
from pstoolkit.sim.scenes import SceneMaps
from pstoolkit_mitsuba.heightfield import covered, height_mesh
from pstoolkit_mitsuba.materials import BSDFS, CONDUCTORS, bsdf_dict
from pstoolkit_mitsuba.shapes import orthographic_sensor, planar_texcoords, triangle_mesh
from pstoolkit_mitsuba.variants import VARIANTS, set_variant


def _floats(values: np.ndarray) -> list[float]:
    """Python floats: the llvm variant's vectors take no numpy scalars."""
    return [float(v) for v in np.ravel(values)]


def _surface(mi: Any, maps: SceneMaps, bsdf: Any) -> Any:
    """The Mitsuba mesh of ``maps``: the mesh it was made from, or else its height field."""
    h, w = maps.mask.shape
    if maps.mesh is not None:
        positions, faces = maps.mesh
        return triangle_mesh(mi, positions, faces, planar_texcoords(positions, h, w), bsdf=bsdf)
    mesh = height_mesh(maps)
    return triangle_mesh(mi, mesh.positions, mesh.faces, mesh.texcoords, mesh.normals, bsdf)


class MitsubaRendering(Rendering):
    """A scene loaded into Mitsuba with one emitter, whose pose and power each image sets: a
    directional one for far lights, a point light for near ones, each scene made on first use (a
    scene holding both would split its light samples between them, one of them dark)."""

    def __init__(self, maps: SceneMaps, seed: int, options: dict[str, Any]) -> None:
        self._mi = set_variant(options["variant"])
        self.variant = self._mi.variant()
        self._maps, self._options = maps, options
        self._spp = int(options["spp"])
        # Mitsuba's seed is a 32-bit unsigned integer
        self._seed = int(seed) % (2**32)
        self._scenes: dict[str, tuple[Any, Any]] = {}
        self.mask = covered(maps.mask) if maps.mesh is None else maps.mask
        self.normal = np.where(self.mask[..., None], maps.normal, 0.0).astype(np.float32)

    def _scene(self, near: bool) -> tuple[Any, Any]:
        """(scene, its parameters) with the point light (``near``) or the directional one."""
        key = "near" if near else "far"
        if key not in self._scenes:
            mi, maps, h, w = self._mi, self._maps, *self._maps.mask.shape
            bsdf = mi.load_dict(bsdf_dict(mi, maps, self._options["bsdf"], self._options["conductor"]))
            emitter = (
                {"type": "point", "position": [0.0, 0.0, 1.0], "intensity": {"type": "rgb", "value": [0.0, 0.0, 0.0]}}
                if near else
                {"type": "directional", "direction": [0.0, 0.0, -1.0], "irradiance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}}
            )
            scene = mi.load_dict({
                "type": "scene",
                "integrator": {"type": "path", "max_depth": int(self._options["max_depth"]), "hide_emitters": True},
                "sensor": orthographic_sensor(mi, h, w, self._spp),
                "surface": _surface(mi, maps, bsdf),
                "light": emitter,
            })
            self._scenes[key] = (scene, mi.traverse(scene))
        return self._scenes[key]

    def _set_far(self, params: Any, direction: np.ndarray, intensity: np.ndarray) -> None:
        mi = self._mi
        d = -np.asarray(direction, dtype=np.float64)
        up = [1.0, 0.0, 0.0] if abs(d[0]) < 0.9 else [0.0, 1.0, 0.0]
        params["light.to_world"] = mi.ScalarTransform4f().look_at(origin=[0, 0, 0], target=_floats(d), up=up)
        params["light.irradiance.value"] = mi.Color3f(*_floats(math.pi * np.asarray(intensity, dtype=np.float64)))

    def _set_near(self, params: Any, light: Any, t_us: float) -> None:
        mi = self._mi
        pitch = float(light.pixel_pitch_mm)
        position = np.asarray(light.position_mm(np.array([t_us])), dtype=np.float64).reshape(3) / pitch
        # the model's intensity is e at the distance √(R² + H²) of its ring: e·(R² + H²)/d² in mm
        reach2 = (float(light.radius_mm) ** 2 + float(light.height_mm) ** 2) / pitch**2
        params["light.position"] = mi.ScalarPoint3f(*_floats(position))
        params["light.intensity.value"] = mi.Color3f(*_floats(math.pi * reach2 * np.asarray(light.intensity, dtype=np.float64)))

    def images(self, light: LightModel, t_us: np.ndarray, progress: Progress = no_progress) -> np.ndarray:
        t_us = np.asarray(t_us, dtype=np.float64).reshape(-1)
        h, w = self.mask.shape
        out = np.empty((len(t_us), h, w, 3), dtype=np.float32)
        if light.near and not hasattr(light, "position_mm"):
            raise UserError(f"light model {light.name!r} is a near light without a position (position_mm): cannot place it")
        scene, params = self._scene(light.near)
        far = None if light.near else light.evaluate(t_us)
        for k, t in enumerate(t_us):
            if far is None:
                self._set_near(params, light, float(t))
            else:
                self._set_far(params, far[0][k], far[1][k])
            params.update()
            image = self._mi.render(scene, spp=self._spp, seed=self._seed)
            out[k] = np.maximum(np.asarray(image, dtype=np.float32)[..., :3], 0.0)
            progress((k + 1) / len(t_us), "renders")
        return out


class MitsubaRenderer(SceneRenderer):
    """Path-traced renders of a scene's height field with Mitsuba 3 (``pip install 'pstoolkit[mitsuba]'``)."""

    name: ClassVar[str] = "mitsuba"
    summary: ClassVar[str] = "Mitsuba 3 path tracer: inter-reflections, rough plastic, copper or principled BSDF, textured albedo"
    options: ClassVar[tuple[Option, ...]] = (
        Option("bsdf", str, BSDFS[0], "Mitsuba BSDF of the surface (albedo map as texture)", choices=BSDFS),
        Option("conductor", str, CONDUCTORS[0], "metal of roughconductor (Mitsuba's measured spectra)", choices=CONDUCTORS),
        Option("spp", int, 16, "samples per pixel of each image", minimum=1, maximum=65536),
        Option("max_depth", int, 4, "longest path, segments: 2 direct light only, 3 one bounce of inter-reflection, …", minimum=2, maximum=64),
        Option("variant", str, VARIANTS[0], "Mitsuba variant: auto (llvm_ad_rgb when DRJIT_LIBLLVM_PATH works, else scalar_rgb), "
               "scalar_rgb or llvm_ad_rgb", choices=VARIANTS),
    )

    def prepare(self, maps: SceneMaps, seed: int, **options: Any) -> MitsubaRendering:
        return MitsubaRendering(maps, seed, options)
