"""Surfaces in result folders: ``pstoolkit run --integrate`` and ``pstoolkit integrate`` write depth,
a 16-bit depth PNG and meshes that an independent reader opens, and the depth error reaches
result.json, ``pstoolkit eval`` and ``pstoolkit report``."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from plyfile import PlyData

import psfmt
from pstoolkit.cli import main
from pstoolkit.io.normalmap import write_normal_npy
from pstoolkit.surface.outputs import PNG_LEVELS, mesh_faces
from pstoolkit.surface.shapes import perspective_sphere
from pstoolkit.testing import sphere_capture

SIZE = 48


@pytest.fixture(scope="module")
def solved(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A Lambertian sphere capture with true depth, solved by frameps with a Poisson surface."""
    root = tmp_path_factory.mktemp("surface")
    capture = sphere_capture(root / "ball.h5", size=SIZE, lights=12)
    out = root / "ball-frameps"
    assert main(["run", str(capture), "--solver", "frameps", "-o", str(out), "--integrate", "poisson"]) == 0
    return capture, out


def test_mesh_faces_cover_each_block_with_two_triangles_facing_the_camera() -> None:
    mask = np.zeros((4, 5), bool)
    mask[1:4, 1:4] = True
    mask[0, 0] = True  # an isolated pixel: a vertex without a face
    flat, faces = mesh_faces(mask)
    assert flat.size == 10 and faces.shape == (8, 3)
    # counter-clockwise seen from +z (x right = column, y up = −row)
    v, u = np.divmod(flat, 5)
    xy = np.stack([u, -v], axis=1)[faces]
    cross = (xy[:, 1, 0] - xy[:, 0, 0]) * (xy[:, 2, 1] - xy[:, 0, 1]) - (xy[:, 1, 1] - xy[:, 0, 1]) * (xy[:, 2, 0] - xy[:, 0, 0])
    assert np.all(cross > 0)
    # a block with three pixels gives the one triangle they make
    mask[3, 3] = False
    assert mesh_faces(mask)[1].shape == (7, 3)


def test_run_integrate_writes_depth_png_and_meshes_with_the_depth_error(solved: tuple[Path, Path]) -> None:
    _, out = solved
    summary = json.loads((out / "result.json").read_text())
    surface = summary["surface"]
    assert surface["integrator"] == "poisson" and surface["projection"] == "orthographic"
    depth = np.load(out / "depth.npy")
    normal = np.load(out / "normal.npy")
    mask = np.any(normal != 0, axis=-1)
    assert depth.dtype == np.float32 and depth.shape == (SIZE, SIZE)
    assert np.isfinite(depth[mask]).all() and np.isnan(depth[~mask]).all()
    # the PNG decodes to the depth within one level, nearer brighter, 0 outside
    png = cv2.imread(str(out / "depth.png"), cv2.IMREAD_UNCHANGED)
    assert png.dtype == np.uint16 and np.all(png[~mask] == 0) and np.all(png[mask] >= 1)
    entry = surface["depth"]
    decoded = entry["offset"] + (png.astype(np.float64) - 1) / PNG_LEVELS * entry["scale"]
    assert np.abs(decoded - depth)[mask].max() <= 0.5 * entry["scale"] / PNG_LEVELS + 1e-4
    centre, rim = png[SIZE // 2, SIZE // 2], png[mask].min()
    assert centre > rim
    # a 48 px sphere from frameps normals (4.9° MAE, worst at the rim): within 6 % of its depth range
    # after scale/offset alignment (from its true normals: 1.0 %)
    error = surface["depth_error"]
    assert error["alignment"].startswith("least-squares scale and offset")
    assert 0 < error["rmse_of_range"] < 0.06 and error["pixels"] == int(mask.sum())


def test_the_ply_mesh_opens_in_an_independent_reader_with_the_expected_counts(solved: tuple[Path, Path]) -> None:
    _, out = solved
    normal = np.load(out / "normal.npy")
    mask = np.any(normal != 0, axis=-1)
    flat, faces = mesh_faces(mask)
    ply = PlyData.read(str(out / "mesh.ply"))
    assert ply["vertex"].count == flat.size == json.loads((out / "result.json").read_text())["surface"]["mesh"]["vertices"]
    assert ply["face"].count == len(faces)
    # vertices in pixel order at their pixel's x, y (orthographic: pixels from the image centre)
    v, u = np.divmod(flat, SIZE)
    np.testing.assert_allclose(ply["vertex"]["x"], u - (SIZE - 1) / 2, atol=1e-4)
    np.testing.assert_allclose(ply["vertex"]["y"], (SIZE - 1) / 2 - v, atol=1e-4)
    obj = (out / "mesh.obj").read_text()
    assert sum(line.startswith("v ") for line in obj.splitlines()) == flat.size
    assert sum(line.startswith("f ") for line in obj.splitlines()) == len(faces)


def test_integrate_a_folder_with_another_integrator_and_show_the_depth_error(
    solved: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str],
) -> None:
    capture, out = solved
    folder = tmp_path / "copy"
    folder.mkdir()
    for name in ("normal.npy", "normal.png", "result.json"):
        (folder / name).write_bytes((out / name).read_bytes())
    # without --capture the path in result.json is not followed: no depth error
    assert main(["integrate", str(folder), "--integrator", "bini"]) == 0
    assert json.loads((folder / "result.json").read_text())["surface"]["depth_error"] is None
    assert main(["integrate", str(folder), "--integrator", "bini", "--capture", str(capture)]) == 0
    surface = json.loads((folder / "result.json").read_text())["surface"]
    assert surface["integrator"] == "bini" and surface["depth_error"]["rmse_of_range"] < 0.06
    capsys.readouterr()
    assert main(["eval", str(folder)]) == 0
    table = capsys.readouterr().out
    assert "Depth RMSE after scale and offset alignment (% of the true depth range)" in table
    assert f"{100 * surface['depth_error']['rmse_of_range']:.1f}" in table.split("Depth RMSE")[1]
    report = tmp_path / "report.md"
    assert main(["report", str(folder), "-o", str(report)]) == 0
    assert "Depth RMSE" in report.read_text()


@pytest.mark.parametrize(("args", "message"), [
    (["--integrator", "nothing"], "unknown integrator 'nothing' (known: "),
    (["--set", "bogus=1"], "bogus"),
])
def test_bad_integrate_arguments_name_the_problem(
    solved: tuple[Path, Path], args: list[str], message: str, capsys: pytest.CaptureFixture[str],
) -> None:
    _, out = solved
    assert main(["integrate", str(out), *args]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1


def test_integrate_refuses_a_folder_without_a_result(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["integrate", str(tmp_path)]) == 2
    assert f"{tmp_path / 'result.json'}: no result.json (not a result folder)" in capsys.readouterr().err


def test_a_perspective_capture_is_integrated_through_its_camera(tmp_path: Path) -> None:
    """A format 1.2 capture with a pinhole camera: ``pstoolkit integrate --capture`` takes its
    intrinsics, integrates in perspective and scores the depth against the capture's (z = −d)."""
    truth = perspective_sphere(64, focal=70.0, distance=3.0, radius=1.0)
    camera = truth.camera
    k = np.array([[camera.fx, 0.0, camera.cx], [0.0, camera.fy, camera.cy], [0.0, 0.0, 1.0]])
    normal = np.where(truth.mask[..., None], truth.normal, 0.0).astype(np.float32)
    capture = tmp_path / "persp.h5"
    shading = np.clip(normal @ np.array([0.3, 0.2, 0.93]), 0.0, None)
    psfmt.write(psfmt.Capture(
        frames=psfmt.Frames(np.repeat(shading[None, ..., None], 3, axis=-1).astype(np.float32),
                            light_direction=np.array([[0.3, 0.2, 0.93]]) / np.linalg.norm([0.3, 0.2, 0.93]),
                            light_intensity=np.ones((1, 3))),
        calibration=psfmt.Calibration(camera_model="perspective", intrinsics=k),
        ground_truth=psfmt.GroundTruth(normal=normal, mask=truth.mask,
                                       depth=np.nan_to_num(truth.depth).astype(np.float32)),
    ), capture)
    folder = tmp_path / "result"
    folder.mkdir()
    write_normal_npy(folder / "normal.npy", normal)
    (folder / "result.json").write_text(json.dumps({"name": "truth", "object": "persp"}))
    assert main(["integrate", str(folder), "--capture", str(capture)]) == 0
    surface = json.loads((folder / "result.json").read_text())["surface"]
    assert surface["projection"] == "perspective"
    # measured 1.0 % of the visible depth range (0.3 % of the diameter) at 64 px, mostly at the rim
    assert surface["depth_error"]["rmse_of_range"] < 0.02
    # the mesh's vertices lie on the pixels' rays through the camera's centre
    ply = PlyData.read(str(folder / "mesh.ply"))
    xyz = np.stack([ply["vertex"][c] for c in "xyz"], axis=1).astype(np.float64)
    v, u = np.divmod(np.flatnonzero(truth.mask), 64)
    np.testing.assert_allclose(xyz[:, 0] / -xyz[:, 2], (u - camera.cx) / camera.fx, atol=1e-5)
    np.testing.assert_allclose(xyz[:, 1] / -xyz[:, 2], -(v - camera.cy) / camera.fy, atol=1e-5)
