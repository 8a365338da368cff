"""``pstoolkit simulate``: valid captures, determinism, classic captures, clean errors; the demo cache."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest

import psfmt
from pstoolkit.cli import main
from pstoolkit.optics.layouts import grid_directions
from pstoolkit.optics.shadow_sweep import shadow_margin, visibility_from_margin
from pstoolkit.plugin.options import defaults
from pstoolkit.sim.config import SimulationConfig
from pstoolkit.sim.demo import demo_capture_path, demo_key
from pstoolkit.sim.scenes import Sphere
from pstoolkit.sim.simulator import DIFFUSE_LEVEL

FAST = ["--size", "32", "--period-ms", "5", "--quiet"]


def datasets(path: Path) -> dict[str, np.ndarray]:
    out: dict[str, np.ndarray] = {}
    with h5py.File(path, "r") as f:
        f.visititems(lambda name, obj: out.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
    return out


def test_simulate_writes_a_valid_hybrid_capture_with_ground_truth(tmp_path: Path) -> None:
    out = tmp_path / "sphere.h5"
    assert main(["simulate", "sphere", "-o", str(out), *FAST]) == 0
    report = psfmt.validate(out)
    assert report.valid, [f.text for f in report.errors]
    with psfmt.read(out) as capture:
        assert capture.kind == "hybrid"
        frames = capture.frames
        assert (frames.count, frames.height, frames.width, frames.channels) == (3, 32, 32, 3)
        assert frames.data.dtype == np.uint8
        assert list(frames.t_start_us) == [0, 1667, 3333] and list(frames.t_end_us) == [1667, 3333, 5000]
        assert (capture.events.width, capture.events.height) == (16, 16)
        events = capture.events.read()
        assert len(events) > 100 and events.t_first_us >= 0 and events.t_last_us <= 5000
        assert set(np.unique(events.p)) == {-1, 1}
        assert capture.lights.model == "ring" and capture.lights.params["elevation_deg"] == 45.0
        np.testing.assert_allclose(capture.calibration.event_to_frame, psfmt.scale_affine(0.5))
        assert capture.calibration.contrast_pos == capture.calibration.contrast_neg == 0.15
        gt = capture.ground_truth
        sphere = Sphere().build(32, 0, **defaults(Sphere.options))
        # bit-equal: simulate stores the float32 maps of this very scene builder
        np.testing.assert_array_equal(gt.normal, sphere.normal)
        np.testing.assert_array_equal(gt.mask, sphere.mask)
        assert set(gt.materials) == {"f0", "roughness", "metallic"}
        assert not frames.frame(0)[~gt.mask].any()  # black background


def test_same_seed_writes_identical_data_and_another_seed_does_not(tmp_path: Path) -> None:
    paths = [tmp_path / f"{name}.h5" for name in ("a", "b", "c")]
    for path, seed in zip(paths, ("7", "7", "8")):
        assert main(["simulate", "blobs", "-o", str(path), "--seed", seed, "--noise", "0.02", *FAST]) == 0
    a, b, c = (datasets(p) for p in paths)
    assert a.keys() == b.keys() and "events/t" in a and "frames/data" in a
    for key in a:
        # bit-equal: the same seed runs the same code on the same machine (determinism, not portability)
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    assert not np.array_equal(a["ground_truth/depth"], c["ground_truth/depth"])


def test_discrete_lights_write_a_classic_capture(tmp_path: Path) -> None:
    out = tmp_path / "classic.h5"
    assert main(["simulate", "sphere", "-o", str(out), "--discrete-lights", "12", "--brdf", "lambertian", *FAST]) == 0
    assert psfmt.validate(out).valid
    with psfmt.read(out) as capture:
        assert capture.kind == "frames" and capture.events is None
        frames = capture.frames
        assert frames.count == 12 and frames.has_instant_lights and not frames.has_windows
        azimuth = np.degrees(np.arctan2(frames.light_direction[:, 1], frames.light_direction[:, 0])) % 360
        np.testing.assert_allclose(azimuth, np.arange(12) * 30.0, atol=1e-6)
        np.testing.assert_allclose(frames.light_direction[:, 2], np.sin(np.radians(45.0)))
        # Lambertian: the brightest value of any frame is the brightest diffuse one, at 80 % of 255
        assert abs(int(frames.data[()].max()) - round(DIFFUSE_LEVEL * 255)) <= 1


def test_bit_depth_12_is_stored_in_uint16_below_4096(tmp_path: Path) -> None:
    out = tmp_path / "deep.h5"
    assert main(["simulate", "relief", "-o", str(out), "--bit-depth", "12", "--discrete-lights", "4", *FAST]) == 0
    with psfmt.read(out) as capture:
        frames = capture.frames
        assert frames.data.dtype == np.uint16 and frames.bit_depth == 12 and frames.saturation == 4095
        assert 2000 < int(frames.data[()].max()) <= 4095


def test_grid_lights_write_96_frames_with_cast_shadows_under_every_light(tmp_path: Path) -> None:
    frames = {}
    for shadows in ("--shadows", "--no-shadows"):
        out = tmp_path / f"grid{shadows}.h5"
        # a fixed gain, so the two captures share their scale whatever their brightest pixel
        args = ["--lights", "grid", "--brdf", "lambertian", "--exposure-gain", "200", shadows]
        assert main(["simulate", "blobs", "-o", str(out), *args, *FAST]) == 0
        assert psfmt.validate(out).valid
        with psfmt.read(out) as capture:
            assert capture.kind == "frames" and capture.events is None and capture.frames.count == 96
            np.testing.assert_allclose(capture.frames.light_direction, grid_directions(), atol=1e-12)
            np.testing.assert_array_equal(capture.frames.light_intensity, np.ones((96, 3)))
            assert capture.lights.model == "sampled" and not capture.lights.params["periodic"]
            np.testing.assert_array_equal(capture.lights.params["times_us"], np.arange(96))
            frames[shadows] = np.asarray(capture.frames.data, dtype=np.float64)
            gt = capture.ground_truth
    visible = visibility_from_margin(shadow_margin(gt.depth, gt.mask, grid_directions()))
    facing = np.einsum("hwc,kc->khw", gt.normal, grid_directions()) > 0.2
    shadowed, lit = (visible < 0.5) & facing & gt.mask, (visible == 1.0) & gt.mask
    assert (shadowed.sum(axis=(1, 2)) > 0).sum() >= 10  # the grid's outer lights cast shadows on blobs
    for k in np.flatnonzero(shadowed.any(axis=(1, 2))):
        dark, bright = frames["--shadows"][k][shadowed[k]], frames["--no-shadows"][k][shadowed[k]]
        assert dark.mean() < 0.5 * bright.mean(), k
        np.testing.assert_array_equal(frames["--shadows"][k][lit[k]], frames["--no-shadows"][k][lit[k]])


def test_a_light_file_sets_directions_and_rgb_intensities(tmp_path: Path) -> None:
    (tmp_path / "light_directions.txt").write_text("0 0 1\n0 0 1\n0.3 0.2 1\n")
    (tmp_path / "light_intensities.txt").write_text("1 1 1\n2 0.5 1\n1 1 1\n")
    out = tmp_path / "file.h5"
    args = ["--lights", str(tmp_path / "light_directions.txt"), "--brdf", "lambertian", "--bit-depth", "16"]
    assert main(["simulate", "sphere", "-o", str(out), *args, *FAST]) == 0
    with psfmt.read(out) as capture:
        frames = capture.frames
        assert frames.count == 3 and not frames.has_windows
        np.testing.assert_allclose(frames.light_direction[2], np.array([0.3, 0.2, 1.0]) / np.linalg.norm([0.3, 0.2, 1.0]), atol=1e-15)
        np.testing.assert_allclose(frames.light_intensity, [[1, 1, 1], [2, 0.5, 1], [1, 1, 1]])
        data = np.asarray(frames.data, dtype=np.float64)
        bright = data[0].min(axis=-1) > 1000
        # the same light at other RGB intensities: each channel scales by its intensity
        np.testing.assert_allclose(data[1][bright] / data[0][bright], np.broadcast_to([2, 0.5, 1], (bright.sum(), 3)), rtol=2e-3)
        # the gain puts the brightest diffuse value (frame 1's red) at 80 % of 16 bit
        assert abs(data.max() - DIFFUSE_LEVEL * 65535) <= 1


def test_peak_auto_gain_keeps_highlights_below_saturation(tmp_path: Path) -> None:
    shiny = ["--set", "f0=0.6", "--set", "roughness=0.1", "--set", "albedo=white", "--discrete-lights", "8"]
    peaks = {}
    for gain in ("diffuse", "peak"):
        out = tmp_path / f"{gain}.h5"
        assert main(["simulate", "sphere", "-o", str(out), "--auto-gain", gain, *shiny, *FAST]) == 0
        with psfmt.read(out) as capture:
            data = np.asarray(capture.frames.data)
            peaks[gain] = (int(data.max()), int((data == 255).sum()))
    assert peaks["diffuse"][0] == 255 and peaks["diffuse"][1] > 8  # a highlight on each frame clips
    assert peaks["peak"] == (round(DIFFUSE_LEVEL * 255), 0)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["sphere", "--size", "4"], "--size 4 must be between 8 and 8192 pixels"),
        (["sphere", "--lights", "grid", "--discrete-lights", "12"], "--discrete-lights 12 must be 96 or 0 (all of them) with --lights grid"),
        (["sphere", "--lights", "gird"], "--lights 'gird' is neither ring, grid nor an existing light_directions.txt file"),
        (["sphere", "--auto-gain", "max"], "--auto-gain 'max' must be diffuse or peak"),
        (["sphere", "--event-scale", "2"], "--event-scale 2.0 must be in (0, 1]"),
        (["sphere", "--bit-depth", "11"], "--bit-depth 11 must be 8, 10, 12 or 16"),
        (["sphere", "--sensor", "evk5"], "--sensor 'evk5': not a sensor preset (choose ideal, evk4, davis346)"),
        (["sphere", "--read-noise-e", "3"], "--read-noise-e 3.0 needs --full-well-e (electrons at saturation)"),
        (["sphere", "--hot-pixel-fraction", "2"], "--hot-pixel-fraction 2.0 must be between 0 and 1"),
        (["sphere", "--sensor", "davis346", "--black-level", "600"], "--black-level 600.0 must be between 0 and half of saturation"),
        (["sphere", "--size", "33"], "is not a whole number of event pixels"),
        (["cube"], "unknown scene 'cube' (known: blobs, chrome-sphere, geometry, hollows, mesh, pits, relief, sphere)"),
        (["sphere", "--set", "bogus=1"], "scene 'sphere' has no option 'bogus'"),
        (["sphere", "--brdf", "phong"], "unknown BRDF 'phong'"),
        (["sphere", "--source", "."], "--source: scene 'sphere' takes no source folder"),
        (["geometry"], "scene 'geometry': needs a source folder (--source DIR)"),
    ],
)
def test_bad_options_exit_2_with_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], message: str) -> None:
    out = tmp_path / "x.h5"
    assert main(["simulate", *args, "-o", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("pstoolkit: error: ") and message in err
    assert not out.exists() and not list(tmp_path.iterdir())


def test_demo_is_generated_once_and_cached_by_its_options(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    config = SimulationConfig(scene="sphere", size=32, period_ms=5.0)
    path = demo_capture_path(config)
    assert path.parent == tmp_path / "cache" / "pstoolkit" and path.name == f"demo-{demo_key(config)}.h5"
    assert psfmt.validate(path).valid
    stamp = path.stat().st_mtime_ns
    assert demo_capture_path(config) == path and path.stat().st_mtime_ns == stamp
    other = SimulationConfig(scene="sphere", size=32, period_ms=5.0, seed=1)
    assert demo_key(other) != demo_key(config)
