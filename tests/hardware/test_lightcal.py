"""``pstoolkit calibrate lights``: light directions from a simulated chrome sphere (frames of discrete
lights, a DiLiGenT-layout folder, a pinhole camera, the ring's events), intensities from a matte
sphere, the near-ring fit, hostile folders, and the ``pstoolkit_register_light_calibrations`` hook."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

import psfmt
from pstoolkit.cli import main
from pstoolkit.hardware.highlight import highlight_direction
from pstoolkit.hardware.ringfit import angles_deg, fit_near_ring
from pstoolkit.hardware.sphere import SphereView, circle_from_mask
from pstoolkit.optics.lights import NearRingLight, RingLight, SampledLight
from pstoolkit.plugin import manager as plugins
from pstoolkit.plugin.manager import get_registries, load_failures
from pstoolkit.sim.config import SimulationConfig
from pstoolkit.sim.simulator import simulate
from pstoolkit.testing import chrome_sphere_pinhole, fake_distribution


@pytest.fixture(scope="module")
def chrome_grid(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 64² chrome sphere under DiLiGenT's 96 grid lights, one 8-bit frame each."""
    path = tmp_path_factory.mktemp("grid") / "chrome.h5"
    simulate(SimulationConfig(scene="chrome-sphere", size=64, lights="grid", seed=0), path)
    return path


@pytest.fixture(scope="module")
def chrome_folder(chrome_grid: Path) -> Path:
    """``chrome_grid`` as a DiLiGenT object folder (16-bit PNGs, mask.png, the true light tables)."""
    folder = chrome_grid.parent / "chromePNG"
    assert main(["export", str(chrome_grid), "--frames", "diligent", "-o", str(folder), "-q"]) == 0
    return folder


def run_json(capsys: pytest.CaptureFixture[str], *argv: str) -> dict:
    capsys.readouterr()
    assert main(list(argv)) == 0
    return json.loads(capsys.readouterr().out)


def test_frames_of_a_capture_give_the_grid_within_half_a_degree(chrome_grid: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "lights"
    report = run_json(capsys, "calibrate", "lights", str(chrome_grid), "-o", str(out), "--json")
    assert (report["method"], report["measured"], report["camera"]) == ("sphere-frames", 96, "orthographic")
    with psfmt.read(chrome_grid) as capture:
        truth = np.asarray(capture.frames.light_direction)
        # no diffuse part: the automatic gain puts the brightest highlight at 80 % of saturation
        assert capture.frames.as_float().max() == pytest.approx(0.8, abs=0.01)
    measured = np.loadtxt(out / "light_directions.txt")
    error = angles_deg(measured, truth)
    assert error.max() < 0.5 and error.mean() < 0.3
    np.testing.assert_allclose(np.loadtxt(out / "light_intensities.txt"), 1.0)
    # lights.json is a --lights file: the sampled model through the measured directions, light k at k µs
    doc = json.loads((out / "lights.json").read_text())
    model = SampledLight.from_spec(psfmt.LightSpec(doc["model"], doc["params"]))
    direction, _ = model.evaluate(np.array([0.0, 95.0]))
    np.testing.assert_allclose(direction, measured[[0, 95]], atol=1e-5)


def test_a_diligent_folder_and_store_into_a_capture(
    chrome_grid: Path, chrome_folder: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = Path(shutil.copytree(chrome_folder, tmp_path / "chromePNG"))
    truth = np.loadtxt(folder / "light_directions.txt")
    target = tmp_path / "scene.h5"
    shutil.copy(chrome_grid, target)
    out = tmp_path / "lights"
    report = run_json(capsys, "calibrate", "lights", str(folder), "-o", str(out), "--store", str(target), "--json")
    assert report["stored_in"] == [str(target)]
    measured = np.loadtxt(out / "light_directions.txt")
    assert angles_deg(measured, truth).max() < 0.5
    with psfmt.read(target) as capture:
        assert capture.lights.model == "sampled"
        np.testing.assert_allclose(capture.frames.light_direction, measured, atol=1e-5)
    # the circle given instead of the mask: the same directions
    (folder / "mask.png").unlink()
    given = run_json(capsys, "calibrate", "lights", str(folder), "--sphere", "31.5,31.5,28.8", "--json")
    assert given["sphere_px"] == [31.5, 31.5, 28.8]
    directions = np.array(given["lights"]["params"]["directions"])
    assert angles_deg(directions, truth).max() < 0.5


def test_intensities_from_a_matte_sphere(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    table = tmp_path / "rig"
    table.mkdir()
    directions = np.array([[0.3, 0.2, 1.0], [-0.4, 0.1, 1.0], [0.0, -0.5, 1.0], [0.2, 0.45, 1.0], [-0.3, -0.3, 1.0]])
    intensities = np.array([[1.0, 1.0, 1.0], [0.5, 0.6, 0.7], [1.2, 1.0, 0.8], [0.8, 0.8, 0.8], [1.0, 0.7, 1.3]])
    np.savetxt(table / "light_directions.txt", directions)
    np.savetxt(table / "light_intensities.txt", intensities)
    chrome, matte = tmp_path / "chrome.h5", tmp_path / "matte.h5"
    simulate(SimulationConfig(scene="chrome-sphere", size=64, lights=str(table / "light_directions.txt"), bit_depth=16), chrome)
    simulate(SimulationConfig(
        scene="sphere", size=64, lights=str(table / "light_directions.txt"), brdf="lambertian", bit_depth=16,
        scene_options=["albedo=white"],
    ), matte)
    report = run_json(capsys, "calibrate", "lights", str(chrome), "--set", f"matte={matte}", "--json")
    got = np.array(report["lights"]["params"]["intensities"])
    np.testing.assert_allclose(got, intensities / intensities.mean(), rtol=0.02)
    assert angles_deg(np.array(report["lights"]["params"]["directions"]), directions / np.linalg.norm(directions, axis=1, keepdims=True)).max() < 0.5


def test_a_pinhole_camera_through_the_intrinsics() -> None:
    size = 96
    k = np.array([[120.0, 0.0, 47.5], [0.0, 120.0, 47.5], [0.0, 0.0, 1.0]])
    centre, radius = np.array([12.0, -6.0, -100.0]), 25.0  # off the axis: the outline is no circle about the centre
    # the outline from the sphere's mask, 4×4 samples a pixel
    coverage = chrome_sphere_pinhole(k, centre, radius, np.array([0.0, 0.0, 1.0]), size, lobe_deg=None)
    circle, outline = circle_from_mask(coverage > 0.5, "mask")
    sphere = SphereView.build(circle, k, outline)
    errors = []
    for light in ([0.3, 0.4, 0.866], [-0.5, 0.1, 0.86], [0.1, -0.6, 0.79]):
        light = np.array(light) / np.linalg.norm(light)
        found = highlight_direction(chrome_sphere_pinhole(k, centre, radius, light, size), sphere, 0.5)
        errors.append(float(angles_deg(found[None], light[None])[0]))
        orthographic = highlight_direction(chrome_sphere_pinhole(k, centre, radius, light, size), SphereView.build(circle), 0.5)
        assert float(angles_deg(orthographic[None], light[None])[0]) > 1.0  # the intrinsics matter here
    assert max(errors) < 0.5, errors


def test_the_ring_from_the_events_of_a_turn(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "ring.h5"
    simulate(SimulationConfig(scene="chrome-sphere", size=64, event_scale=1.0, periods=1, refractory_us=10.0, seed=0), path)
    out = tmp_path / "lights"
    report = run_json(capsys, "calibrate", "lights", str(path), "-o", str(out), "--json")
    assert report["method"] == "sphere-events" and report["lights"]["model"] == "ring"
    assert report["residual_deg"] < 2.0 and report["windows"] >= 30
    doc = json.loads((out / "lights.json").read_text())
    fitted = RingLight.from_spec(psfmt.LightSpec(doc["model"], doc["params"]))
    with psfmt.read(path) as capture:
        truth = RingLight.from_spec(capture.lights)
    t = np.linspace(0.0, truth.period_us, 90, endpoint=False)
    assert angles_deg(fitted.evaluate(t)[0], truth.evaluate(t)[0]).max() < 0.5
    assert abs(fitted.period_us / truth.period_us - 1.0) < 0.005
    # stored into a capture, the model keeps the capture's own period (its frames are timed by it)
    target = tmp_path / "scene.h5"
    shutil.copy(path, target)
    assert main(["calibrate", "lights", str(path), "--store", str(target), "-q"]) == 0
    with psfmt.read(target) as capture:
        stored = RingLight.from_spec(capture.lights)
    assert stored.period_us == truth.period_us and stored.elevation_deg == pytest.approx(fitted.elevation_deg)


def test_the_near_ring_fit_tells_radius_and_height_apart() -> None:
    truth = NearRingLight(radius_mm=120.0, height_mm=90.0, pixel_pitch_mm=0.1, period_us=50_000.0, phase_deg=30.0)
    rng = np.random.default_rng(0)
    t = np.linspace(0.0, 100_000.0, 300)
    # the highlight's points on a sphere of 10 mm off the ring's axis, wandering over it
    points = np.array([25.0, -15.0, 10.0]) + 10.0 * rng.normal(0.0, 0.3, (len(t), 3))
    offset = truth.position_mm(t) - points
    directions = offset / np.linalg.norm(offset, axis=1, keepdims=True)
    fit = fit_near_ring(t, directions, points, 0.1)
    assert abs(fit.light.radius_mm / 120.0 - 1) < 0.01 and abs(fit.light.height_mm / 90.0 - 1) < 0.01
    assert fit.rms_deg < 1e-3 and abs(fit.light.period_us / 50_000.0 - 1) < 1e-4


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda d: (d / "filenames.txt").write_text("../outside.png\n"), "is not a file name inside"),
        (lambda d: (d / "001.png").write_bytes(b"GIF89a not a png at all"), "001.png: not a PNG image"),
        (lambda d: (d / "001.png").write_bytes(bytes.fromhex("89504e470d0a1a0a0000000d49484452") + (1 << 20).to_bytes(4, "big") * 2),
         "more than the"),
        (lambda d: (d / "filenames.txt").write_text(""), "lists no images"),
    ],
)
def test_hostile_folders_are_one_line_errors(
    mutate, message: str, chrome_folder: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]  # type: ignore[no-untyped-def]
) -> None:
    folder = Path(shutil.copytree(chrome_folder, tmp_path / "obj"))
    mutate(folder)
    capsys.readouterr()
    assert main(["calibrate", "lights", str(folder), "-o", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err
    assert not (tmp_path / "out").exists()


def test_bad_arguments_are_one_line_errors(chrome_grid: Path, capsys: pytest.CaptureFixture[str]) -> None:
    for argv, message in [
        (["calibrate", "lights", str(chrome_grid), "--sphere", "1,2"], "expected cx,cy,r"),
        (["calibrate", "lights", str(chrome_grid), "-o", str(chrome_grid)], "exists and is not a folder"),
        (["calibrate", "lights", str(chrome_grid), "--method", "none"], "unknown light calibration 'none'"),
        (["calibrate", "lights", str(chrome_grid), "--method", "sphere-events"], "holds no events of the sphere"),
    ]:
        capsys.readouterr()
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1, err


FIXED = """
    import numpy as np

    from pstoolkit import LightCalibration, LightFit, Option, SampledLight, hookimpl

    class Overhead(LightCalibration):
        name = "overhead"
        summary = "one light straight above, whatever the source"
        options = (Option("brightness", float, 1.0, "its intensity", minimum=0.0),)

        def calibrate(self, source, **options):
            l, e = np.array([[0.0, 0.0, 1.0]]), np.full((1, 3), options["brightness"])
            light = SampledLight(times_us=np.zeros(1), directions=l, intensities=e)
            return LightFit(spec=light.to_spec(), directions=l, intensities=e, times_us=np.zeros(1))

    @hookimpl
    def pstoolkit_register_light_calibrations(registry):
        registry.register(Overhead)
    """


def test_hook_pstoolkit_register_light_calibrations(
    pstoolkit_plugins_alone: pytest.MonkeyPatch, chrome_grid: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    fake_distribution(tmp_path, "pskfake-overhead", "1.0", {"overhead": "pskfake_overhead"}, {"pskfake_overhead": FIXED})
    pstoolkit_plugins_alone.syspath_prepend(str(tmp_path))
    pstoolkit_plugins_alone.setenv(plugins.ALLOW_ENV, "overhead")
    entry = get_registries().light_calibrations.get("overhead")
    assert (entry.plugin, entry.kind) == ("overhead", "light calibration") and load_failures() == []
    report = run_json(capsys, "calibrate", "lights", str(chrome_grid), "--method", "overhead", "--set", "brightness=2", "--json")
    assert report["lights"]["params"]["intensities"] == [[2.0, 2.0, 2.0]] and report["residual_deg"] is None
