"""``pstoolkit export CAPTURE --frames diligent -o DIR``: every field of a classic capture written as a
DiLiGenT object folder and read back by ``convert diligent``; 8-, 12-bit and grey frames scaled to 16
bit exactly; refusals; the folder written as a unit; and the semi-real recipe on a rendered shape
(simulate under the grid → export → ``convert diligent --semi-real``)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest
import scipy.io

import psfmt
import pstoolkit.io.diligent_export
from pstoolkit.cli import main
from pstoolkit.errors import UserError
from pstoolkit.io.diligent_export import export_diligent
from pstoolkit.optics.layouts import grid_directions
from pstoolkit.sim.config import SimulationConfig
from pstoolkit.sim.simulator import simulate
from pstoolkit_diligent.folder import scan_object
from pstoolkit_diligent.rendered import semi_real_from_capture
from pstoolkit_diligent.semireal import BOUNDARY_LOOP


@pytest.fixture(scope="module")
def grid8(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """blobs under the 96 grid lights, 8-bit, 32 px, with ground truth."""
    path = tmp_path_factory.mktemp("grid8") / "blobs96.h5"
    simulate(SimulationConfig(scene="blobs", size=32, lights="grid"), path)
    return path


def cli(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    capsys.readouterr()
    code = main(args)
    out, err = capsys.readouterr()
    return code, out, err


def siblings(folder: Path) -> list[str]:
    """Names beside ``folder`` other than the inputs a test made there."""
    return sorted(p.name for p in folder.parent.iterdir() if p.suffix != ".h5")


def test_every_field_is_written_and_read_back_by_convert_diligent(grid8: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    folder = tmp_path / "blobsPNG"
    code, out, err = cli(["export", str(grid8), "--frames", "diligent", "-o", str(folder)], capsys)
    assert (code, err) == (0, "")
    assert out == f"wrote {folder}: 96 images at 32×32, mask from the ground truth, Normal_gt.mat\n"
    names = [f"{k:03d}.png" for k in range(1, 97)]
    assert (folder / "filenames.txt").read_text().splitlines() == names
    expected = sorted([*names, "filenames.txt", "light_directions.txt", "light_intensities.txt", "mask.png", "Normal_gt.mat"])
    assert sorted(p.name for p in folder.iterdir()) == expected
    with psfmt.read(grid8) as source:
        frames = np.asarray(source.frames.data)
        directions, intensities = source.frames.light_direction, source.frames.light_intensity
        gt = source.ground_truth
    # on disk: 16-bit, BGR as OpenCV writes DiLiGenT's images, 8-bit values ×257
    first = cv2.imread(str(folder / "001.png"), cv2.IMREAD_UNCHANGED)
    assert first.dtype == np.uint16 and first.shape == (32, 32, 3)
    np.testing.assert_array_equal(first[..., ::-1], frames[0].astype(np.uint16) * 257)
    mask_png = cv2.imread(str(folder / "mask.png"), cv2.IMREAD_UNCHANGED)
    assert mask_png.dtype == np.uint8 and mask_png.shape == (32, 32, 3) and set(np.unique(mask_png)) <= {0, 255}
    np.testing.assert_array_equal(mask_png[..., 0] == 255, gt.mask)
    normal_gt = scipy.io.loadmat(folder / "Normal_gt.mat")["Normal_gt"]
    assert normal_gt.dtype == np.float64 and normal_gt.shape == (32, 32, 3)
    np.testing.assert_array_equal(normal_gt[gt.mask], gt.normal[gt.mask])
    assert not normal_gt[~gt.mask].any()
    np.testing.assert_array_equal(np.loadtxt(folder / "light_directions.txt"), directions)  # 17 digits: exact
    np.testing.assert_array_equal(np.loadtxt(folder / "light_intensities.txt"), intensities)

    back = tmp_path / "back.h5"
    assert cli(["convert", "diligent", str(folder), "-o", str(back)], capsys)[0] == 0
    with psfmt.read(back) as capture:
        got = capture.frames
        assert got.data.dtype == np.uint16 and got.saturation == 65535 and got.count == 96
        np.testing.assert_array_equal(np.asarray(got.data), frames.astype(np.uint16) * 257)
        np.testing.assert_allclose(got.light_direction, directions, atol=1e-15)
        np.testing.assert_array_equal(got.light_intensity, intensities)
        np.testing.assert_array_equal(capture.ground_truth.mask, gt.mask)
        np.testing.assert_allclose(capture.ground_truth.normal, gt.normal, atol=1e-7)
    # and the same normals from both: the frames relative to saturation are the same values
    mae = []
    for capture in (grid8, back):
        outdir = tmp_path / f"{capture.stem}-frameps"
        assert cli(["run", str(capture), "--solver", "frameps", "-o", str(outdir)], capsys)[0] == 0
        mae.append(json.loads((outdir / "result.json").read_text())["mae_deg"])
    assert mae[0] < 6.0 and mae[1] == pytest.approx(mae[0], abs=1e-6)


def _classic(path: Path, data: np.ndarray, **frame_attrs: object) -> Path:
    count = len(data)
    directions = np.tile([0.0, 0.0, 1.0], (count, 1))
    frames = psfmt.Frames(data, light_direction=directions, light_intensity=np.full((count, 3), 2.0), **frame_attrs)  # type: ignore[arg-type]
    psfmt.write(psfmt.Capture(frames=frames), path)
    return path


def test_12_bit_grey_frames_with_a_black_level_scale_exactly_and_the_mask_comes_from_the_frames(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    data = rng.integers(64, 4096, (3, 8, 10, 1)).astype(np.uint16)
    data[:, :2] = 64  # a black strip: outside the mask made from the frames
    source = _classic(tmp_path / "grey.h5", data, color_order="L", bit_depth=12, saturation=4095.0, black_level=64.0)
    written = export_diligent(source, tmp_path / "greyPNG")
    assert (written.images, written.height, written.width, written.mask_source, written.normal) == (3, 8, 10, "frames", False)
    obj = scan_object(tmp_path / "greyPNG", require_normal=False)
    assert obj.normal is None
    np.testing.assert_array_equal(obj.mask, np.arange(8)[:, None].repeat(10, axis=1) >= 2)
    np.testing.assert_array_equal(obj.intensities, np.full((3, 3), 2.0))
    for k in range(3):
        image = obj.image(k).astype(np.int64)
        assert np.array_equal(image[..., 0], image[..., 1]) and np.array_equal(image[..., 0], image[..., 2])
        expected = np.rint((data[k, ..., 0].astype(np.float64) - 64) * 65535 / (4095 - 64))
        np.testing.assert_array_equal(image[..., 0], expected)
        # exactly invertible: 12-bit values come back from the 16-bit ones
        np.testing.assert_array_equal(np.rint(image[..., 0] * (4095 - 64) / 65535) + 64, data[k, ..., 0])


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--frames", "png"], "--frames 'png' is not one of diligent"),
        ([], "give exactly one of --events FORMAT and --frames FORMAT"),
        (["--frames", "diligent", "--events", "evt3"], "give exactly one of --events FORMAT and --frames FORMAT"),
        (["--frames", "diligent", "--compression", "none"], "--compression is for --events dsec only"),
    ],
)
def test_option_errors_are_one_line(args: list[str], message: str, grid8: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = cli(["export", str(grid8), *args, "-o", str(tmp_path / "x")], capsys)
    assert (code, out) == (2, "") and err == f"pstoolkit: error: {message}\n"
    assert not list(tmp_path.iterdir())


def test_a_hybrid_capture_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    hybrid = tmp_path / "hybrid.h5"
    assert main(["simulate", "sphere", "-o", str(hybrid), "--size", "16", "--period-ms", "3", "-q"]) == 0
    code, out, err = cli(["export", str(hybrid), "--frames", "diligent", "-o", str(tmp_path / "sphere")], capsys)
    assert (code, out) == (2, "") and err.count("\n") == 1
    assert f"{hybrid}: a hybrid capture of long exposures cannot be a DiLiGenT folder" in err
    assert siblings(tmp_path / "sphere") == []


def test_an_existing_folder_is_kept_unless_forced_then_replaced_whole(grid8: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    folder = tmp_path / "blobsPNG"
    folder.mkdir()
    (folder / "notes.txt").write_text("mine")
    code, out, err = cli(["export", str(grid8), "--frames", "diligent", "-o", str(folder)], capsys)
    assert (code, out) == (2, "") and err == f"pstoolkit: error: {folder}: folder exists and is not empty (give --force to replace it)\n"
    assert [p.name for p in folder.iterdir()] == ["notes.txt"]
    assert cli(["export", str(grid8), "--frames", "diligent", "-o", str(folder), "--force", "-q"], capsys) == (0, "", "")
    assert not (folder / "notes.txt").exists() and len(list(folder.glob("*.png"))) == 97
    assert siblings(folder) == ["blobsPNG"]
    # an empty folder is filled without --force
    empty = tmp_path / "empty"
    empty.mkdir()
    assert cli(["export", str(grid8), "--frames", "diligent", "-o", str(empty), "-q"], capsys)[0] == 0
    assert (empty / "096.png").is_file()


@pytest.mark.parametrize("existing", [False, True])
def test_a_failure_midway_leaves_no_folder_and_the_old_one_intact(existing: bool, grid8: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    folder = tmp_path / "blobsPNG"
    if existing:
        folder.mkdir()
        (folder / "notes.txt").write_text("mine")
    written = []
    real = pstoolkit.io.diligent_export.write_png

    def failing(path: Path, image: np.ndarray) -> None:
        if len(written) == 5:
            raise KeyboardInterrupt
        real(path, image)
        written.append(path)

    monkeypatch.setattr(pstoolkit.io.diligent_export, "write_png", failing)
    with pytest.raises(KeyboardInterrupt):
        export_diligent(grid8, folder, force=True)
    assert len(written) == 5 and all(p.parent != folder for p in written)
    if existing:
        assert [p.name for p in folder.iterdir()] == ["notes.txt"]
        assert siblings(folder) == ["blobsPNG"]
    else:
        assert siblings(folder) == []


def test_semi_real_recipe_on_a_rendered_grid_capture(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rendered = tmp_path / "blobs96.h5"
    simulate(SimulationConfig(scene="blobs", size=64, lights="grid", bit_depth=16, auto_gain="peak",
                              scene_options=["f0=0.3", "roughness=0.2"]), rendered)
    folder = tmp_path / "blobsPNG"
    assert cli(["export", str(rendered), "--frames", "diligent", "-o", str(folder), "-q"], capsys)[0] == 0
    semi = tmp_path / "blobs-semi.h5"
    assert cli(["convert", "diligent", str(folder), "--semi-real", "--size", "64", "-o", str(semi), "-q"], capsys)[0] == 0
    report = psfmt.validate(semi)
    assert report.valid, [f.text for f in report.errors]
    with psfmt.read(semi) as capture:
        assert capture.kind == "hybrid" and capture.frames.count == 3 and capture.frames.data.dtype == np.uint8
        np.testing.assert_allclose(capture.lights.params["directions"], grid_directions()[list(BOUNDARY_LOOP)], atol=1e-15)
        frames = np.asarray(capture.frames.data)
        mask = capture.ground_truth.mask
        events = capture.events.read()
        # the highlights of the shiny surface clip the 8-bit long exposures, the diffuse surface does not
        assert 0 < (frames[:, mask] == 255).mean() < 0.2
    fired = np.zeros((32, 32), dtype=bool)
    fired[events.y, events.x] = True
    assert fired[mask[::2, ::2]].mean() > 0.9
    # the Python helper runs the same chain: the same capture
    helper = semi_real_from_capture(rendered, tmp_path / "helper.h5", size=64)
    with h5py.File(semi, "r") as a, h5py.File(helper, "r") as b:
        for key in ("frames/data", "events/t", "events/x", "events/y", "events/p", "ground_truth/normal"):
            np.testing.assert_array_equal(a[key][()], b[key][()], err_msg=key)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["blobs-semi.h5", "blobs96.h5", "blobsPNG", "helper.h5"]
    # the three long exposures carry the shape (6.9° with frameps on this 64 px capture)
    outdir = tmp_path / "frameps"
    assert cli(["run", str(semi), "--solver", "frameps", "-o", str(outdir)], capsys)[0] == 0
    assert json.loads((outdir / "result.json").read_text())["mae_deg"] < 9.0


def test_semi_real_helper_rejects_unknown_settings(grid8: Path, tmp_path: Path) -> None:
    with pytest.raises(UserError, match="semi_real_from_capture: no setting 'refractory'"):
        semi_real_from_capture(grid8, tmp_path / "x.h5", refractory=2000.0)
    with pytest.raises(UserError, match="option contrast: 0.001 is below the minimum 0.01"):
        semi_real_from_capture(grid8, tmp_path / "x.h5", contrast=0.001)
    assert not list(tmp_path.iterdir())
