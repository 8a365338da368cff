"""The ``mitsuba`` renderer (plugins/pstoolkit_mitsuba) on tiny scenes: a DiLiGenT folder that the
semi-real recipe reads, a direct hybrid capture a solver recovers a sphere from, inter-reflection in
a concavity, and the BSDF and texture options. Skipped without the ``mitsuba`` extra."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mitsuba")

import psfmt  # noqa: E402
import pstoolkit  # noqa: E402
from pstoolkit.cli import main  # noqa: E402
from pstoolkit.evaluation.metrics import angular_error_deg  # noqa: E402
from pstoolkit.optics.layouts import layout_light  # noqa: E402
from pstoolkit.plugin.manager import get_registries  # noqa: E402
from pstoolkit.sim.scenes import assemble, build_materials, normals_from_height  # noqa: E402
from pstoolkit_mitsuba import render_scene  # noqa: E402

FAST = {"spp": 4, "variant": "scalar_rgb"}


def rendering(maps, **options):
    entry = get_registries().renderers.get("mitsuba")
    return entry.obj().prepare(maps, 0, **entry.parse_options([f"{k}={v}" for k, v in {**FAST, **options}.items()]))


def scene(name: str, size: int, *assignments: str):
    entry = get_registries().scenes.get(name)
    return entry.obj().build(size, 0, **entry.parse_options(list(assignments)))


def overhead(*directions: tuple[float, float, float]):
    d = np.asarray(directions, dtype=np.float64)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return layout_light(d, np.ones_like(d)), np.arange(len(d), dtype=np.float64)


def test_diligent_folder_round_trips_through_the_semi_real_recipe(tmp_path: Path) -> None:
    folder = tmp_path / "spherePNG"
    written = render_scene("sphere", size=32, diligent=folder, **{**FAST, "spp": 16})["diligent"]
    assert (written.images, written.height, written.width, written.normal) == (96, 32, 32, True)
    assert main(["convert", "diligent", str(folder), "--semi-real", "--size", "32", "-o", str(tmp_path / "s.h5"), "-q"]) == 0
    report = psfmt.validate(tmp_path / "s.h5")
    assert report.valid and not report.warnings
    with psfmt.read(tmp_path / "s.h5") as capture:
        assert capture.kind == "hybrid" and len(capture.events) > 200
        truth = capture.ground_truth
        # the sphere's truth comes back through the crop and resize of the recipe
        z = truth.normal[..., 2][truth.mask]
        assert truth.mask.sum() > 100 and z.min() > 0 and np.median(z) > 0.6
    # the folder as a classic capture of its 96 lights: least squares on lights near the view axis,
    # where the plastic's highlights in the middle of the sphere are the error
    assert main(["convert", "diligent", str(folder), "-o", str(tmp_path / "grid.h5"), "-q"]) == 0
    stats = pstoolkit.solve_capture(tmp_path / "grid.h5", "frameps", device="cpu").score.stats
    assert stats["mae_deg"] < 7.0 and stats["median_deg"] < 4.5


def test_direct_capture_validates_and_a_solver_recovers_a_sphere(tmp_path: Path) -> None:
    out = tmp_path / "sphere.h5"
    written = render_scene("sphere", size=32, capture=out, key_step_deg=4.0, **FAST)["capture"]
    assert written.frames == 3 and written.events > 500 and written.event_size == (16, 16)
    report = psfmt.validate(out)
    assert report.valid and not report.warnings
    with psfmt.read(out) as capture:
        assert capture.lights.model == "ring" and capture.calibration.refractory_us == 2000.0
        normal, mask = capture.ground_truth.normal, capture.ground_truth.mask
        # the truth is the pixels the mesh covers wholly: the scene's mask less its rim
        assert 500 < mask.sum() < scene("sphere", 32).mask.sum()
    # dualres's closed-form start (epochs=0): the rough plastic's highlight ring is the main error
    solution = pstoolkit.solve_capture(out, "dualres", device="cpu", epochs=0)
    error = angular_error_deg(solution.normal, normal, mask)[mask]
    assert np.median(error) < 5.5 and np.mean(error < 20.0) > 0.97


def test_inter_reflection_lights_a_concavity() -> None:
    """A V-groove of 45° walls under a light from above: its floor receives the light its walls
    reflect, which a path of 2 segments (direct light only) leaves out."""
    size = 24
    u = np.abs(np.arange(size) - (size - 1) / 2.0)
    height = np.broadcast_to(np.minimum(u, 8.0), (size, size)).astype(np.float64)
    mask = np.ones((size, size), bool)
    materials = build_materials(mask, np.random.default_rng(0), {"albedo": "white", "f0": 0.04, "roughness": 0.6,
                                                                "varying": False, "metallic": 0.0})
    maps = assemble(normals_from_height(height), height, mask, materials)
    light, t_us = overhead((0.0, 0.0, 1.0))
    groove = (slice(4, -4), slice(5, -5))
    direct = rendering(maps, max_depth=2, spp=16).images(light, t_us)[0][groove].mean()
    bounced = rendering(maps, max_depth=4, spp=16).images(light, t_us)[0][groove].mean()
    assert bounced > 1.12 * direct  # 0.439 against 0.369: +19 %


def test_plugins_lists_the_renderer_with_its_flag(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["plugins"]) == 0
    out = capsys.readouterr().out
    assert "  renderers:\n    mitsuba  Mitsuba 3 path tracer" in out and "      --render-set spp (int, default 16)" in out


def test_bsdf_and_texture_options_take_effect() -> None:
    light, t_us = overhead((0.3, 0.2, 1.0))
    textured = scene("sphere", 24)
    white = scene("sphere", 24, "albedo=white")
    plastic = rendering(textured, spp=16).images(light, t_us)[0]
    mask = rendering(textured).mask
    plain = rendering(white, spp=16).images(light, t_us)[0]
    # the texture: the ratio of textured to white renders follows the albedo map
    ratio = plastic[mask] / np.maximum(plain[mask], 1e-6)
    assert np.corrcoef(ratio[:, 1], textured.albedo[mask][:, 1])[0, 1] > 0.9
    copper = rendering(textured, bsdf="roughconductor").images(light, t_us)[0]
    principled = rendering(textured, bsdf="principled").images(light, t_us)[0]
    # copper reflects red over blue; a dielectric's diffuse colour is the texture's
    assert copper[mask][:, 0].mean() > 1.5 * copper[mask][:, 2].mean()
    assert np.abs(principled[mask] - plastic[mask]).mean() > 0.01
    assert np.abs(copper[mask] - plastic[mask]).mean() > 0.05


def test_a_mesh_file_is_a_scene_the_renderer_draws(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    trimesh = pytest.importorskip("trimesh")
    path = tmp_path / "ball.ply"
    trimesh.creation.icosphere(subdivisions=4, radius=3.0).export(path)
    maps = scene("mesh", 24, f"source={path}", "albedo=white")
    assert maps.mesh is not None and maps.mask.sum() > 250
    # the rasterised normals are the sphere's: the ball fills 0.9 of the frame, centred
    v, u = np.nonzero(maps.mask)
    x, y = (u + 0.5 - 12.0) / 10.8, (12.0 - v - 0.5) / 10.8
    truth = np.stack([x, y, np.sqrt(np.clip(1.0 - x * x - y * y, 0.0, None))], axis=-1)
    error = np.degrees(np.arccos(np.clip(np.sum(maps.normal[v, u] * truth, axis=-1), -1.0, 1.0)))
    assert np.median(error) < 2.0
    light, t_us = overhead((0.0, 0.0, 1.0))
    image = rendering(maps, spp=16, bsdf="principled").images(light, t_us)[0][..., 1]
    # lit from the view direction the ball is brightest where it faces the camera
    centre, rim = image[maps.mask & (maps.normal[..., 2] > 0.95)].mean(), image[maps.mask & (maps.normal[..., 2] < 0.5)].mean()
    assert centre > 1.5 * rim
    (tmp_path / "broken.ply").write_bytes(b"ply\nformat nonsense\n")
    assert main(["simulate", "mesh", "--source", str(tmp_path / "broken.ply"), "--size", "16", "--renderer", "mitsuba",
                 "-o", str(tmp_path / "x.h5")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "broken.ply" in err and not (tmp_path / "x.h5").exists()


def test_a_distant_near_light_renders_as_the_ring_and_noise_is_low() -> None:
    """A point light on a ring 3·10⁴ pixels away lights a 24-pixel sphere like the directional ring
    light of the same elevation; and two seeds differ by little (one emitter per scene, so every
    light sample is of the light)."""
    maps = scene("sphere", 24, "albedo=white")
    t_us = np.array([0.0, 250.0])
    far = pstoolkit.RingLight(elevation_deg=45.0, period_us=1000.0)
    near = pstoolkit.NearRingLight(radius_mm=1000.0, height_mm=1000.0, pixel_pitch_mm=0.05, period_us=1000.0)
    first = rendering(maps, spp=16)
    a, b = first.images(far, t_us), first.images(near, t_us)
    mask = first.mask
    assert np.abs(a - b)[:, mask].mean() < 0.01 * a[:, mask].mean()
    entry = get_registries().renderers.get("mitsuba")
    other = entry.obj().prepare(maps, 1, **entry.parse_options(["spp=16", "variant=scalar_rgb"])).images(far, t_us)
    assert np.abs(a - other)[:, mask].mean() < 0.03 * a[:, mask].mean()
