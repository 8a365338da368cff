"""``pstoolkit convert diligent|diligent-pi`` on generated DiLiGenT-layout folders: exact frames and
lights (RGB vs OpenCV's BGR), recovery of the known normals by ``frameps``, the semi-real hybrid and
discrete captures, several objects, bad input, and the generic converter flags."""

from __future__ import annotations

import json
import os
import shutil
import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
from helpers.diligent import Fixture, write_diligent, write_diligent_pi

import psfmt
from pstoolkit.cli import main
from pstoolkit.errors import UserError
from pstoolkit.plugin.options import Option, parse_assignments
from pstoolkit_diligent.semireal import BOUNDARY_LOOP

SEMI_SIZE = 32


@pytest.fixture(scope="module")
def ball(tmp_path_factory: pytest.TempPathFactory) -> Fixture:
    return write_diligent(tmp_path_factory.mktemp("pmsData") / "ballPNG")


def convert(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    capsys.readouterr()
    code = main(["convert", *args])
    out, err = capsys.readouterr()
    return code, out, err


def frameps_mae(capture: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> float:
    outdir = tmp_path / f"{capture.stem}-frameps"
    capsys.readouterr()
    assert main(["run", str(capture), "--solver", "frameps", "-o", str(outdir), "--json"]) == 0
    capsys.readouterr()
    return json.loads((outdir / "result.json").read_text())["mae_deg"]


def test_frames_lights_and_truth_are_the_folder_exactly(ball: Fixture, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "ball.h5"
    assert convert(["diligent", str(ball.folder), "-o", str(out)], capsys) == (0, f"wrote {out}\n", "")
    assert psfmt.validate(out).valid
    with psfmt.read(out) as capture:
        frames = capture.frames
        assert frames is not None and capture.events is None
        assert (frames.count, frames.height, frames.width, frames.channels) == (96, 64, 76, 3)
        assert frames.data.dtype == np.uint16 and frames.saturation == 65535.0 and frames.color_order == "RGB"
        np.testing.assert_array_equal(np.asarray(frames.data), np.rint(ball.radiance).astype(np.uint16))
        np.testing.assert_allclose(frames.light_intensity, ball.intensities, atol=5e-7)
        np.testing.assert_allclose(frames.light_direction, ball.directions, atol=1e-6)
        gt = capture.ground_truth
        assert gt is not None
        np.testing.assert_array_equal(gt.mask, ball.mask)
        np.testing.assert_allclose(gt.normal, ball.normal, atol=1e-6)


def test_convert_then_frameps_recovers_the_normals_within_1_degree(ball: Fixture, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "ball.h5"
    assert convert(["diligent", str(ball.folder), "-o", str(out)], capsys)[0] == 0
    assert frameps_mae(out, tmp_path, capsys) < 1.0


def test_very_different_rgb_intensities_are_divided_channel_by_channel(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    fixture = write_diligent(tmp_path / "redPNG", seed=3, rgb_spread=(4.0, 1.0, 0.25))
    out = tmp_path / "red.h5"
    assert convert(["diligent", str(fixture.folder), "-o", str(out)], capsys)[0] == 0
    with psfmt.read(out) as capture:
        frames = capture.frames
        assert frames is not None
        divided = np.asarray(frames.data, dtype=np.float64) / frames.light_intensity[:, None, None, :]
    # divided by its own light, every frame shows albedo × shading: the same colour under all 96 lights
    lit = divided[:, fixture.mask]
    ratio = lit[..., 0] / lit[..., 2]
    expected = fixture.albedo[fixture.mask][:, 0] / fixture.albedo[fixture.mask][:, 2]
    np.testing.assert_allclose(ratio, np.broadcast_to(expected, ratio.shape), rtol=1e-2)  # 16-bit rounding of dim blue
    assert frameps_mae(out, tmp_path, capsys) < 1.0


def semi_real(ball: Fixture, tmp_path: Path, capsys: pytest.CaptureFixture[str], *extra: str) -> Path:
    out = tmp_path / "semi.h5"
    code, _, err = convert(["diligent", str(ball.folder), "-o", str(out), "--size", str(SEMI_SIZE), *extra], capsys)
    assert (code, err) == (0, "")
    return out


def test_semi_real_capture_layout(ball: Fixture, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = semi_real(ball, tmp_path, capsys, "--semi-real", "--period-ms", "36")
    report = psfmt.validate(out)
    assert report.valid and not report.warnings, [f.text for f in report.errors + report.warnings]
    with psfmt.read(out) as capture:
        frames, events, lights = capture.frames, capture.events, capture.lights
        assert frames is not None and events is not None and lights is not None
        assert np.asarray(frames.data).shape == (3, SEMI_SIZE, SEMI_SIZE, 3) and frames.data.dtype == np.uint8
        np.testing.assert_array_equal(frames.t_start_us, [0, 12000, 24000])
        np.testing.assert_array_equal(frames.t_end_us, [12000, 24000, 36000])
        assert (events.width, events.height) == (SEMI_SIZE // 2, SEMI_SIZE // 2)
        assert lights.model == "sampled" and lights.params["periodic"] and lights.params["period_us"] == 36000
        np.testing.assert_array_equal(lights.params["times_us"], np.arange(36) * 1000)
        np.testing.assert_allclose(lights.params["directions"], ball.directions[list(BOUNDARY_LOOP)], atol=1e-6)
        np.testing.assert_array_equal(lights.params["intensities"], np.ones((36, 3)))
        calibration = capture.calibration
        assert (calibration.contrast_pos, calibration.contrast_neg, calibration.refractory_us) == (0.15, 0.15, 2000.0)
        np.testing.assert_allclose(calibration.event_to_frame, psfmt.scale_affine(0.5))
        gt = capture.ground_truth
        assert gt is not None and gt.normal.shape == (SEMI_SIZE, SEMI_SIZE, 3)
        inside = np.linalg.norm(gt.normal[gt.mask], axis=-1)
        np.testing.assert_allclose(inside, 1.0, atol=1e-5)
        # the square crop is the disc's extent plus 2 × 16 px, scaled to SEMI_SIZE
        side = np.ptp(np.nonzero(ball.mask)[0]) + 1 + 32
        assert gt.mask.sum() == pytest.approx(ball.mask.sum() * (SEMI_SIZE / side) ** 2, rel=0.05)
        window = events.window(0, 36000)
        x, y, p = window.x, window.y, window.p
    # every pixel fires at most once per refractory period (+1), and the masked pixels all change by far more than C
    n_pixels = (SEMI_SIZE // 2) ** 2
    assert len(p) <= n_pixels * (36000 // 2000 + 1)
    fired = np.zeros((SEMI_SIZE // 2, SEMI_SIZE // 2), dtype=bool)
    fired[y, x] = True
    event_mask = cv2.resize(gt.mask.astype(np.float32), (SEMI_SIZE // 2, SEMI_SIZE // 2), interpolation=cv2.INTER_AREA) == 1.0
    assert fired[event_mask].mean() > 0.95
    # one closed light loop: each pixel ends where it started, so rises and falls balance
    assert abs(int(np.sum(p == 1)) - int(np.sum(p == -1))) <= 0.1 * len(p)


def test_semi_real_frames_recover_the_normals_and_events_are_seeded(ball: Fixture, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = semi_real(ball, tmp_path, capsys, "--semi-real")
    # three long exposures with the equivalent lights of the sampled model agree with the resized truth
    assert frameps_mae(out, tmp_path, capsys) < 1.0
    again = tmp_path / "again"
    again.mkdir()
    second = semi_real(ball, again, capsys, "--semi-real")
    with psfmt.read(out) as a, psfmt.read(second) as b:
        assert a.events is not None and b.events is not None and len(a.events) > 0
        first, other = a.events.window(0, 10**6), b.events.window(0, 10**6)
        for column in "xytp":
            # bit-equal: two conversions of the same files by the same code on the same machine
            np.testing.assert_array_equal(getattr(first, column), getattr(other, column))
        np.testing.assert_array_equal(np.asarray(a.frames.data), np.asarray(b.frames.data))


def test_discrete_lights_capture(ball: Fixture, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = semi_real(ball, tmp_path, capsys, "--discrete-lights", "12")
    assert psfmt.validate(out).valid
    with psfmt.read(out) as capture:
        frames = capture.frames
        assert capture.events is None and frames is not None
        assert np.asarray(frames.data).shape == (12, SEMI_SIZE, SEMI_SIZE, 3) and frames.data.dtype == np.uint8
        picked = [BOUNDARY_LOOP[j] for j in range(0, 36, 3)]
        np.testing.assert_allclose(frames.light_direction, ball.directions[picked], atol=1e-6)
        np.testing.assert_array_equal(frames.light_intensity, np.ones((12, 3)))
        assert not frames.has_windows
    assert frameps_mae(out, tmp_path, capsys) < 1.0


def corrupt(path: Path) -> None:
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))


def drop_last_line(path: Path) -> None:
    path.write_text("".join(path.read_text().splitlines(keepends=True)[:-1]))


BREAKAGES = {
    "missing file": (lambda f: (f / "light_intensities.txt").unlink(), "light_intensities.txt: file does not exist"),
    "count mismatch": (
        lambda f: drop_last_line(f / "light_directions.txt"),
        ": the numbers of images and lights differ (filenames.txt has 96, light_directions.txt has 95, light_intensities.txt has 96 lines)",
    ),
    "8-bit image": (
        lambda f: cv2.imwrite(str(f / "005.png"), np.full((64, 76, 3), 128, np.uint8)),
        "005.png: 8-bit image, expected a 16-bit PNG",
    ),
    "corrupted PNG": (lambda f: corrupt(f / "042.png"), "042.png: corrupted PNG (checksum mismatch in chunk 'IDAT')"),
    "missing ground truth": (lambda f: (f / "Normal_gt.mat").unlink(), "Normal_gt.mat: file does not exist"),
}


@pytest.mark.parametrize("breakage", sorted(BREAKAGES))
@pytest.mark.parametrize("mode", [[], ["--semi-real", "--size", "16"]])
def test_bad_input_is_one_line_exit_2_and_no_output(
    breakage: str, mode: list[str], ball: Fixture, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = tmp_path / "ballPNG"
    shutil.copytree(ball.folder, folder)
    damage, message = BREAKAGES[breakage]
    damage(folder)
    outdir = tmp_path / "out"
    outdir.mkdir()
    code, out, err = convert(["diligent", str(folder), "-o", str(outdir / "ball.h5"), *mode], capsys)
    assert (code, out) == (2, "")
    assert err.count("\n") == 1 and err.startswith("pstoolkit: error: ") and err.rstrip().endswith(message), err
    assert list(outdir.iterdir()) == []


@pytest.fixture(scope="module")
def pms_root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("multi") / "pmsData"
    write_diligent(root / "ballPNG", seed=1, height=40, width=48)
    write_diligent(root / "catPNG", seed=2, height=40, width=48)
    return root


@pytest.mark.parametrize("selection", [["--object", "ball", "--object", "catPNG"], ["--all"], ["--set", "object=ball", "--object", "cat"]])
def test_several_objects_become_one_file_each(
    selection: list[str], pms_root: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "captures"
    code, stdout, _ = convert(["diligent", str(pms_root), "-o", str(out), *selection], capsys)
    assert code == 0
    assert stdout == f"wrote {out / 'ball.h5'}\nwrote {out / 'cat.h5'}\n"
    for name in ("ball", "cat"):
        with psfmt.read(out / f"{name}.h5") as capture:
            assert capture.frames is not None and capture.frames.count == 96 and capture.frames.width == 48
            assert capture.description.startswith(f"{name}PNG converted by pstoolkit convert diligent")


def test_all_writes_a_folder_even_for_one_object(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 24 B.4: with --all the root decides how many objects there are, so OUT is always a
    folder (created) holding <object>.h5 — one object too — and a file in its way is an error."""
    root = tmp_path / "pmsData"
    write_diligent(root / "bearPNG", seed=3, height=24, width=28)
    out = tmp_path / "dil"
    code, stdout, _ = convert(["diligent", str(root), "--all", "-o", str(out)], capsys)
    assert code == 0 and stdout == f"wrote {out / 'bear.h5'}\n"
    assert out.is_dir() and sorted(p.name for p in out.iterdir()) == ["bear.h5"]
    with psfmt.read(out / "bear.h5") as capture:
        assert capture.frames is not None and capture.frames.count == 96 and capture.frames.width == 28
    # one named object still goes to OUT as a file
    single = tmp_path / "bear.h5"
    assert convert(["diligent", str(root), "--object", "bear", "-o", str(single)], capsys)[0] == 0
    assert single.is_file()
    code, _, err = convert(["diligent", str(root), "--all", "-o", str(single)], capsys)
    assert code == 2 and err == f"pstoolkit: error: {single}: is a file, but --all writes an output folder\n"


def test_one_bad_object_stops_all_before_writing(pms_root: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    root = tmp_path / "pmsData"
    shutil.copytree(pms_root, root)
    corrupt(root / "catPNG" / "096.png")
    out = tmp_path / "captures"
    code, _, err = convert(["diligent", str(root), "--all", "-o", str(out)], capsys)
    assert code == 2 and "catPNG/096.png: corrupted PNG" in err
    assert not out.exists()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--object", "dog"], "no object folder dog or dogPNG"),
        ([], "has no filenames.txt; give an object folder, or the dataset root with --object NAME or --all"),
        (["--all", "--object", "ball"], "give --object NAME or --all, not both"),
    ],
)
def test_object_selection_errors(args: list[str], message: str, pms_root: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = convert(["diligent", str(pms_root), "-o", str(tmp_path / "x"), *args], capsys)
    assert code == 2 and err.rstrip().endswith(message), err


def test_diligent_pi_with_and_without_ground_truth(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with_gt = write_diligent_pi(tmp_path / "Pi" / "Flower")
    write_diligent_pi(tmp_path / "Pi" / "Queen", seed=1, normal_gt=False)
    out = tmp_path / "pi"
    assert convert(["diligent-pi", str(tmp_path / "Pi"), "--all", "-o", str(out)], capsys)[0] == 0
    with psfmt.read(out / "Flower.h5") as capture:
        assert capture.frames is not None and np.asarray(capture.frames.data).shape == (100, 48, 48, 3)
        np.testing.assert_array_equal(np.asarray(capture.frames.data), np.rint(with_gt.radiance).astype(np.uint16))
    with psfmt.read(out / "Queen.h5") as capture:
        assert capture.ground_truth is not None and capture.ground_truth.normal is None
        np.testing.assert_array_equal(capture.ground_truth.mask, with_gt.mask)
    assert frameps_mae(out / "Flower.h5", tmp_path, capsys) < 1.0
    small = tmp_path / "small.h5"
    assert convert(["diligent-pi", str(with_gt.folder), "-o", str(small), "--size", "24"], capsys)[0] == 0
    with psfmt.read(small) as capture:
        data = np.asarray(capture.frames.data)
        assert data.shape == (100, 24, 24, 3) and data.dtype == np.uint16
        # 2 × 2 area averages of the stored frames
        full = np.rint(with_gt.radiance).reshape(100, 24, 2, 24, 2, 3).mean(axis=(2, 4))
        assert np.abs(data - full).max() <= 0.5 + 1e-6
    assert frameps_mae(small, tmp_path, capsys) < 1.5


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--semi-reel"], ("converter 'diligent' has no option --semi-reel (options: --all, --contrast, --discrete-lights, "
                           "--event-scale, --frames, --object, --period-ms, --periods, --refractory-rule, --refractory-us, "
                           "--seed, --semi-real, --size; see `pstoolkit convert NAME --help`)")),
        (["--size"], "--size needs a value (int)"),
        (["--size", "big"], "option size: expected int, got 'big'"),
        (["--contrast", "0.2"], "--contrast: only with --semi-real or --discrete-lights"),
        (["--semi-real", "--discrete-lights", "4"], "--semi-real and --discrete-lights K are two different captures: give one"),
        (["--semi-real", "--size", "30", "--event-scale", "0.25"], "--size 30 × --event-scale 0.25 = 7.5 is not a whole number of event pixels"),
        (["--set", "semi_real=maybe"], "option semi_real: expected true or false, got 'maybe'"),
        (["extra"], "convert diligent: expected one SRC (a file or folder), got {src} extra"),
    ],
)
def test_flag_errors(args: list[str], message: str, ball: Fixture, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    tokens = ["diligent", str(ball.folder), "-o", str(tmp_path / "x.h5"), *args]
    code, _, err = convert(tokens, capsys)
    assert code == 2 and err == f"pstoolkit: error: {message.format(src=ball.folder)}\n", err
    assert not (tmp_path / "x.h5").exists()


def test_flags_and_set_are_the_same_options(ball: Fixture, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    a, b = tmp_path / "a.h5", tmp_path / "b.h5"
    assert convert(["diligent", "--discrete-lights=6", str(ball.folder), "--size", "16", "-o", str(a), "--no-semi-real"], capsys)[0] == 0
    assert convert(["diligent", str(ball.folder), "-o", str(b), "--set", "discrete_lights=6", "--set", "size=16"], capsys)[0] == 0
    with psfmt.read(a) as x, psfmt.read(b) as y:
        np.testing.assert_array_equal(np.asarray(x.frames.data), np.asarray(y.frames.data))
        assert np.asarray(x.frames.data).shape == (6, 16, 16, 3)


def test_help_lists_converters_and_their_flags(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = convert(["--help"], capsys)
    assert code == 0 and "diligent     DiLiGenT object folders" in out and "diligent-pi  DiLiGenT-Π object folders" in out
    code, out, _ = convert(["diligent", "--help"], capsys)
    assert code == 0 and out.startswith("Usage: pstoolkit convert diligent SRC -o OUT [OPTIONS]")
    assert "  --object (STR, repeatable, default none): " in out and "  --semi-real (flag, default False): " in out
    code, _, err = convert(["nope", "src", "-o", "x"], capsys)
    assert code == 2 and err == "pstoolkit: error: unknown converter 'nope' (known: dat, diligent, diligent-pi, dsec, hdf5, raw)\n"


def test_repeatable_option_collects_values_and_keeps_its_default() -> None:
    options = (Option("object", str, (), "objects", multiple=True), Option("size", int, 0, "size"))
    assert parse_assignments([], options, owner="x") == {"object": (), "size": 0}
    assert parse_assignments(["object=a", "size=3", "object=b"], options, owner="x") == {"object": ("a", "b"), "size": 3}
    with_default = (Option("tag", str, ("d",), "tags", multiple=True, choices=("d", "e")),)
    assert parse_assignments([], with_default, owner="x") == {"tag": ("d",)}
    assert parse_assignments(["tag=e"], with_default, owner="x") == {"tag": ("e",)}
    with pytest.raises(UserError, match="option tag: 'f' is not one of d, e"):
        parse_assignments(["tag=f"], with_default, owner="x")


def test_files_outside_the_object_folder_are_refused(ball: Fixture, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 19, item 11: names in filenames.txt that climb out, absolute names and symbolic links
    that lead out of the object folder are refused before anything is read through them."""
    folder = tmp_path / "ballPNG"
    shutil.copytree(ball.folder, folder)
    listing = folder / "filenames.txt"
    names = listing.read_text().splitlines()
    secret = tmp_path / "outside" / "secret.png"
    secret.parent.mkdir()
    shutil.copy(folder / names[0], secret)
    out = tmp_path / "ball.h5"
    for listed in ("../outside/secret.png", str(secret)):
        listing.write_text("\n".join([listed, *names[1:]]) + "\n")
        code, _, err = convert(["diligent", str(folder), "-o", str(out)], capsys)
        assert (code, err) == (2, f"pstoolkit: error: {listing}: {listed!r} lies outside the object folder {folder}: refused\n")
    listing.write_text("\n".join(names) + "\n")
    (folder / names[0]).unlink()
    os.symlink(secret, folder / names[0])
    code, _, err = convert(["diligent", str(folder), "-o", str(out)], capsys)
    assert (code, err) == (2, f"pstoolkit: error: {listing}: {names[0]!r} lies outside the object folder {folder}: refused\n")
    assert not out.exists()


def test_a_png_that_does_not_inflate_is_one_line_without_libpng_s_own(ball: Fixture, tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    """Issue 19, item 15: image data that does not inflate (checksums intact) is our one line on
    stderr, without the line libpng prints itself."""
    folder = tmp_path / "ballPNG"
    shutil.copytree(ball.folder, folder)
    image = folder / "042.png"
    data = bytearray(image.read_bytes())
    at = data.find(b"IDAT")
    length = struct.unpack(">I", data[at - 4 : at])[0]
    data[at + 4 + 2 : at + 4 + 6] = b"\xff\xff\xff\xff"  # inside the deflate stream, after its zlib header
    data[at + 4 + length : at + 8 + length] = struct.pack(">I", zlib.crc32(bytes(data[at : at + 4 + length])))
    image.write_bytes(bytes(data))
    capfd.readouterr()
    assert main(["convert", "diligent", str(folder), "-o", str(tmp_path / "ball.h5")]) == 2
    assert capfd.readouterr() == ("", f"pstoolkit: error: {image}: corrupted PNG (the image data cannot be decoded)\n")
