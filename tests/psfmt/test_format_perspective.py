"""Format 1.2's perspective camera (spec/hybrid-capture.md §9.1): the projection's conventions, every
validation error with its message, the writer's refusals, and files of the versions before it.

Faulty files are made by writing a valid capture and breaking it with h5py, as in test_format_faults.py.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path

import h5py
import numpy as np
import pytest
from helpers.captures import sample_capture
from helpers.format_versions import OLD_VERSIONS, old_capture, old_file

import psfmt
from psfmt.camera import pixel_rays, project
from pstoolkit.cli import main

K = np.array([[500.0, 0.0, 31.5], [0.0, 510.0, 30.25], [0.0, 0.0, 1.0]])
Edit = Callable[[h5py.File], None]


# the projection ----------------------------------------------------------------------------------
def test_the_spec_example_back_projects_and_projects() -> None:
    k = np.array([[1200.0, 0.0, 319.5], [0.0, 1200.0, 239.5], [0.0, 0.0, 1.0]])
    np.testing.assert_array_equal(pixel_rays(k, 919.5, 239.5), [0.5, 0.0, -1.0])
    np.testing.assert_array_equal(400.0 * pixel_rays(k, 919.5, 239.5), [200.0, 0.0, -400.0])
    np.testing.assert_array_equal(project(k, [200.0, 0.0, -400.0]), [919.5, 239.5])
    # the principal point looks down the optical axis, −z
    np.testing.assert_array_equal(pixel_rays(k, 319.5, 239.5), [0.0, 0.0, -1.0])


def test_rays_follow_the_conventions_of_the_spec() -> None:
    """u right is +x, v down is −y, the scene at z < 0; the depth d along the axis is −z."""
    right, below = pixel_rays(K, K[0, 2] + 10, K[1, 2]), pixel_rays(K, K[0, 2], K[1, 2] + 10)
    assert right[0] > 0 and right[1] == 0 and right[2] == -1
    assert below[0] == 0 and below[1] < 0 and below[2] == -1
    np.testing.assert_allclose(right, [10 / 500.0, 0.0, -1.0])
    np.testing.assert_allclose(below, [0.0, -10 / 510.0, -1.0])


@pytest.mark.parametrize("skew", [0.0, 2.5])
def test_projection_inverts_back_projection(skew: float) -> None:
    k = K.copy()
    k[0, 1] = skew
    v, u = np.mgrid[0:48, 0:64].astype(np.float64)
    depth = 300.0 + 50.0 * np.random.default_rng(0).random(u.shape)  # d = −z, mm
    points = depth[..., None] * pixel_rays(k, u, v)
    assert points.shape == (48, 64, 3)
    np.testing.assert_allclose(points[..., 2], -depth)
    np.testing.assert_allclose(project(k, points), np.stack([u, v], axis=-1), atol=1e-9)
    # K applied to (x, −y, −z) gives the pixel, as the spec states
    image = np.einsum("ij,...j->...i", k, points * [1.0, -1.0, -1.0])
    np.testing.assert_allclose(image[..., :2] / image[..., 2:], np.stack([u, v], axis=-1), atol=1e-9)


# validation --------------------------------------------------------------------------------------
def written(tmp_path: Path, camera: str = "perspective") -> Path:
    capture = sample_capture("hybrid", seed=0, n_events=3000)
    if camera == "perspective":
        capture.calibration.camera_model = "perspective"
        capture.calibration.intrinsics = K
    path = tmp_path / "capture.h5"
    psfmt.write(capture, path)
    return path


def set_intrinsics(values: object) -> Edit:
    def edit(f: h5py.File) -> None:
        del f["calibration/intrinsics"]
        f["calibration/intrinsics"] = values

    return edit


def poke_k(row: int, col: int, value: float) -> Edit:
    k = K.copy()
    k[row, col] = value
    return set_intrinsics(k)


def set_camera(value: object) -> Edit:
    def edit(f: h5py.File) -> None:
        f["calibration"].attrs["camera_model"] = value

    return edit


def add_intrinsics(f: h5py.File) -> None:
    f["calibration/intrinsics"] = K


def huge_intrinsics(f: h5py.File) -> None:
    """A declared (100000, 100000) float64 (80 GB) with no data stored: refused before it is read."""
    del f["calibration/intrinsics"]
    f["calibration"].create_dataset("intrinsics", shape=(100_000, 100_000), dtype=np.float64, chunks=(1, 1000))


def intrinsics_group(f: h5py.File) -> None:
    del f["calibration/intrinsics"]
    f["calibration"].create_group("intrinsics")


ORTHO = "orthographic"
SHAPE = "has shape (3, 3) and dtype {}, expected (3, 3) float64"
ERRORS: dict[str, tuple[str, Edit, str]] = {
    "perspective without intrinsics": (
        "perspective", lambda f: f.__delitem__("calibration/intrinsics"),
        "/calibration: camera_model 'perspective' needs the dataset 'intrinsics' (3, 3) float64, which is missing",
    ),
    "intrinsics with orthographic": (
        ORTHO, add_intrinsics, "/calibration/intrinsics: is given, but camera_model is 'orthographic': only a perspective camera has intrinsics",
    ),
    "intrinsics without camera_model": (
        ORTHO, lambda f: (add_intrinsics(f), f["calibration"].attrs.__delitem__("camera_model")),
        "/calibration/intrinsics: is given, but camera_model is 'orthographic': only a perspective camera has intrinsics",
    ),
    "intrinsics of wrong shape": (
        "perspective", set_intrinsics(K[:2]), "/calibration/intrinsics: has shape (2, 3) and dtype float64, expected (3, 3) float64",
    ),
    "intrinsics a scalar": (
        "perspective", set_intrinsics(np.float64(500.0)), "/calibration/intrinsics: has shape () and dtype float64, expected (3, 3) float64",
    ),
    "intrinsics float32": ("perspective", set_intrinsics(K.astype(np.float32)), "/calibration/intrinsics: " + SHAPE.format("float32")),
    "intrinsics integers": ("perspective", set_intrinsics(K.astype(np.int64)), "/calibration/intrinsics: " + SHAPE.format("int64")),
    "intrinsics a group": ("perspective", intrinsics_group, "/calibration/intrinsics: must be a dataset (3, 3) float64"),
    "NaN in intrinsics": ("perspective", poke_k(0, 2, np.nan), "/calibration/intrinsics: holds NaN or infinite values"),
    "infinite intrinsics": ("perspective", poke_k(1, 1, np.inf), "/calibration/intrinsics: holds NaN or infinite values"),
    "fx zero": ("perspective", poke_k(0, 0, 0.0), "/calibration/intrinsics: fx and fy must be positive, got fx = 0, fy = 510"),
    "fy negative": ("perspective", poke_k(1, 1, -510.0), "/calibration/intrinsics: fx and fy must be positive, got fx = 500, fy = -510"),
    "K[1][0] not 0": (
        "perspective", poke_k(1, 0, 0.5),
        "/calibration/intrinsics: element [1, 0] is 0.5, expected 0 (K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]])",
    ),
    "last row scaled": ("perspective", set_intrinsics(2 * K), "/calibration/intrinsics: last row is (0, 0, 2), expected (0, 0, 1)"),
    "last row not (0, 0, 1)": ("perspective", poke_k(2, 0, 1e-3), "/calibration/intrinsics: last row is (0.001, 0, 1), expected (0, 0, 1)"),
    "unknown camera model": ("perspective", set_camera("fisheye\x1b[2J"), "/calibration: camera_model 'fisheye\\x1b[2J' is not defined in format 1.3"),
    "camera model not a string": (ORTHO, set_camera(np.array([1, 2])), "/calibration: camera_model array([1, 2]) is not defined in format 1.3"),
    "perspective in a 1.1 file": (
        "perspective", lambda f: f.attrs.__setitem__("format_version", "1.1"),
        "/calibration: camera_model 'perspective' needs format 1.2 or later, but the file is format 1.1",
    ),
    "huge intrinsics": (
        "perspective", huge_intrinsics,
        "/calibration/intrinsics: declares (100000, 100000) float64 (80,000,000,000 bytes) but the file stores no data for it",
    ),
}


@pytest.mark.parametrize("name", ERRORS)
def test_camera_error_is_caught_with_its_message(tmp_path: Path, name: str, capsys: pytest.CaptureFixture[str]) -> None:
    camera, edit, message = ERRORS[name]
    path = written(tmp_path, camera)
    with h5py.File(path, "r+") as f:
        edit(f)
    for reader in (lambda: psfmt.read(path), lambda: psfmt.load(path)):
        with pytest.raises(psfmt.FormatError) as caught:
            reader()
        assert str(caught.value) == f"{path}: {message}"
    report = psfmt.validate(path)
    assert [f.text for f in report.errors] == [message]
    capsys.readouterr()
    assert main(["validate", str(path)]) == 1
    out, err = capsys.readouterr()
    assert err == "" and [x for x in out.splitlines() if ": error: " in x] == [f"{path}: error: {message}"]


def test_big_endian_intrinsics_are_valid_and_read_as_native_float64(tmp_path: Path) -> None:
    path = written(tmp_path)
    with h5py.File(path, "r+") as f:
        set_intrinsics(K.astype(">f8"))(f)
    assert psfmt.validate(path).errors == []
    calibration = psfmt.load(path).calibration
    np.testing.assert_array_equal(calibration.intrinsics, K)
    assert calibration.intrinsics.dtype == np.dtype(np.float64)


def test_a_newer_minor_version_may_use_the_perspective_camera(tmp_path: Path) -> None:
    path = written(tmp_path)
    with h5py.File(path, "r+") as f:
        f.attrs["format_version"] = "1.7"
    report = psfmt.validate(path)
    assert report.errors == [] and [w.text for w in report.warnings] == [
        "/: written by format 1.7, newer than 1.3: parts this reader does not know are ignored"]
    np.testing.assert_array_equal(psfmt.load(path).calibration.intrinsics, K)


@pytest.mark.parametrize(("camera", "intrinsics", "message"), [
    ("perspective", None, "calibration: camera_model 'perspective' needs intrinsics, the (3, 3) matrix K"),
    ("orthographic", K, "calibration: intrinsics are given, but camera_model is 'orthographic'"),
    ("perspective", K[:2], "calibration: intrinsics has shape (2, 3), expected (3, 3)"),
    ("perspective", 2 * K, "calibration: intrinsics last row is (0, 0, 2), expected (0, 0, 1)"),
    ("perspective", -K, "calibration: intrinsics fx and fy must be positive, got fx = -500, fy = -510"),
    ("pinhole", K, "calibration: camera_model 'pinhole' is not one of orthographic, perspective"),
])
def test_the_writer_refuses_a_camera_the_validator_would(tmp_path: Path, camera: str, intrinsics: object, message: str) -> None:
    capture = sample_capture("events", seed=1)
    capture.calibration.camera_model = camera
    capture.calibration.intrinsics = intrinsics
    path = tmp_path / "c.h5"
    with pytest.raises(psfmt.FormatError) as caught:
        psfmt.write(capture, path)
    assert str(caught.value) == f"{path}: {message}"
    assert list(tmp_path.iterdir()) == []


# files of earlier versions -----------------------------------------------------------------------
def expected_old(version: str) -> psfmt.Capture:
    capture = old_capture(version)
    if version == "1.0":
        assert capture.calibration.refractory_rule is None
    return capture


@pytest.mark.parametrize("version", OLD_VERSIONS)
def test_files_of_earlier_versions_validate_and_read_as_before(version: str) -> None:
    path = old_file(version)
    report = psfmt.validate(path)
    assert report.errors == [] and not any("format" in w.text for w in report.warnings)
    expected = expected_old(version)
    with psfmt.read(path, verify=True) as capture:
        assert capture.format_version == version
        c, e = capture.calibration, expected.calibration
        assert (c.camera_model, c.intrinsics, c.refractory_rule) == ("orthographic", None, e.refractory_rule)
        assert (c.contrast_pos, c.contrast_neg, c.refractory_us) == (e.contrast_pos, e.contrast_neg, e.refractory_us)
        np.testing.assert_array_equal(c.event_to_frame, e.event_to_frame)
        np.testing.assert_array_equal(c.view_direction, e.view_direction)
        np.testing.assert_array_equal(capture.frames.data[()], expected.frames.data)
        np.testing.assert_array_equal(capture.events.read().t, expected.events.data.t)
        np.testing.assert_array_equal(capture.ground_truth.depth, expected.ground_truth.depth)
        assert capture.lights.params["period_us"] == 3000 and sorted(capture.results) == ["eventps"]


@pytest.mark.parametrize("version", OLD_VERSIONS)
def test_intrinsics_in_a_file_before_1_2_are_an_unknown_part(tmp_path: Path, version: str) -> None:
    """Before 1.2 ``intrinsics`` is no part of the format: ignored (even malformed), as it always was."""
    path = tmp_path / "old.h5"
    shutil.copyfile(old_file(version), path)
    with h5py.File(path, "r+") as f:
        f["calibration/intrinsics"] = np.full((2, 2), np.nan, np.float32)
    assert psfmt.validate(path).errors == []
    assert psfmt.load(path).calibration.intrinsics is None


@pytest.mark.parametrize("version", OLD_VERSIONS)
def test_an_old_file_rewritten_is_the_current_version_with_the_same_content(tmp_path: Path, version: str) -> None:
    with psfmt.read(old_file(version)) as old:
        psfmt.write(old, tmp_path / "new.h5")
    assert psfmt.validate(tmp_path / "new.h5").errors == []
    new = psfmt.load(tmp_path / "new.h5")
    assert new.format_version == "1.3" and new.calibration.camera_model == "orthographic"
    assert new.calibration.refractory_rule == expected_old(version).calibration.refractory_rule


def test_an_orthographic_1_2_file_holds_what_a_1_1_writer_wrote_but_the_version(tmp_path: Path) -> None:
    """So a 1.1 reader reads it (with its newer-version warning): 1.2 adds nothing to such a file."""
    path = tmp_path / "new.h5"
    psfmt.write(old_capture("1.1"), path)

    def items(file: Path) -> dict[str, object]:
        found: dict[str, object] = {}
        with h5py.File(file, "r") as f:
            def visit(name: str, obj: object) -> None:
                attrs = {k: np.asarray(v).tolist() for k, v in obj.attrs.items()}  # type: ignore[attr-defined]
                shape = (obj.shape, obj.dtype.str) if isinstance(obj, h5py.Dataset) else "group"
                found[name] = (shape, attrs)

            visit("/", f)
            f.visititems(visit)
        return found

    old, new = items(old_file("1.1")), items(path)
    assert old["/"][1].pop("format_version") == "1.1" and new["/"][1].pop("format_version") == "1.3"  # type: ignore[index]
    assert new == old
