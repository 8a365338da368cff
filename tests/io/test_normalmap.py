"""Normal maps on disk: 8/16-bit PNG round trips, the community colour convention, BGR, npy, geometry folders."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from pstoolkit.errors import UserError
from pstoolkit.evaluation.metrics import angular_error_deg
from pstoolkit.io.normalmap import (
    normal_to_rgb,
    read_geometry_folder,
    read_normal_npy,
    read_normal_png,
    rgb_to_normal,
    write_normal_npy,
    write_normal_png,
)


def _sphere(size: int = 48) -> tuple[np.ndarray, np.ndarray]:
    """Normals of a sphere filling the image (x right, y up, z to the camera) and its mask."""
    v, u = np.mgrid[0:size, 0:size].astype(np.float64)
    x = (u - (size - 1) / 2) / (size / 2 - 1)
    y = ((size - 1) / 2 - v) / (size / 2 - 1)
    mask = x * x + y * y < 1
    z = np.sqrt(np.clip(1 - x * x - y * y, 0, None))
    normal = np.stack([x, y, z], axis=-1)
    normal[~mask] = 0
    return normal, mask


def test_facing_camera_and_background_values() -> None:
    normal = np.zeros((2, 2, 3))
    normal[0, 0] = [0, 0, 1]
    normal[0, 1] = [1, 0, 0]
    mask = np.array([[True, True], [False, False]])
    rgb16 = normal_to_rgb(normal, mask, bits=16)
    assert rgb16.dtype == np.uint16
    np.testing.assert_array_equal(rgb16[0, 0], [32768, 32768, 65535])
    np.testing.assert_array_equal(rgb16[0, 1], [65535, 32768, 32768])
    np.testing.assert_array_equal(rgb16[1], 0)
    rgb8 = normal_to_rgb(normal, mask, bits=8)
    assert rgb8.dtype == np.uint8
    np.testing.assert_array_equal(rgb8[0, 0], [128, 128, 255])
    np.testing.assert_array_equal(rgb8[1], 0)


@pytest.mark.parametrize(("bits", "max_error_deg"), [(16, 0.01), (8, 0.4)])
def test_png_round_trip_within_quantisation(tmp_path: Path, bits: int, max_error_deg: float) -> None:
    normal, mask = _sphere()
    path = tmp_path / f"normal{bits}.png"
    write_normal_png(path, normal, mask, bits=bits)
    back, back_mask = read_normal_png(path)
    assert back.dtype == np.float32 and back.shape == normal.shape
    np.testing.assert_array_equal(back_mask, mask)
    assert np.all(back[~mask] == 0)
    errors = angular_error_deg(back, normal, mask)
    assert np.nanmax(errors) < max_error_deg
    assert list(tmp_path.iterdir()) == [path]  # the atomic temporary file is gone


def test_png_is_rgb_on_disk(tmp_path: Path) -> None:
    """OpenCV reads BGR: a normal pointing right (x = +1) must be red in the file, i.e. last in cv2's order."""
    normal = np.tile([1.0, 0.0, 0.0], (4, 4, 1))
    normal[0, 0] = [0.0, -1.0, 0.0]  # pointing down: green channel 0
    path = tmp_path / "right.png"
    write_normal_png(path, normal, np.ones((4, 4), bool))
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16
    np.testing.assert_array_equal(raw[1, 1], [32768, 32768, 65535])  # B, G, R
    np.testing.assert_array_equal(raw[0, 0], [32768, 0, 32768])


def test_rgb_to_normal_decodes_both_depths() -> None:
    normal, mask = rgb_to_normal(np.array([[[128, 128, 255], [0, 0, 0]]], dtype=np.uint8))
    np.testing.assert_array_equal(mask, [[True, False]])
    np.testing.assert_allclose(normal[0, 0], [0, 0, 1], atol=5e-3)
    np.testing.assert_array_equal(normal[0, 1], 0)
    normal16, _ = rgb_to_normal(np.array([[[32768, 65535, 32768]]], dtype=np.uint16))
    np.testing.assert_allclose(normal16[0, 0], [0, 1, 0], atol=1e-4)


def test_npy_round_trip_is_exact(tmp_path: Path) -> None:
    normal, _ = _sphere(32)
    path = tmp_path / "normal.npy"
    write_normal_npy(path, normal)
    back = read_normal_npy(path)
    assert back.dtype == np.float32
    np.testing.assert_array_equal(back, normal.astype(np.float32))
    assert list(tmp_path.iterdir()) == [path]


def test_geometry_folder(tmp_path: Path) -> None:
    normal, mask = _sphere(40)
    rgb = np.clip(np.floor((normal + 1) / 2 * 65535 + 0.5), 0, 65535).astype(np.uint16)
    rgb[~mask] = 65535  # such folders may use a white background: the mask must come from mask.png
    cv2.imwrite(str(tmp_path / "normal_map.png"), rgb[..., ::-1])
    cv2.imwrite(str(tmp_path / "mask.png"), mask.astype(np.uint8) * 255)
    depth = np.linspace(1400, 1500, 40 * 40, dtype=np.float32).reshape(40, 40)
    np.savez(tmp_path / "depth_gt.npz", depth_gt=depth)
    got_normal, got_mask, got_depth = read_geometry_folder(tmp_path)
    np.testing.assert_array_equal(got_mask, mask)
    np.testing.assert_array_equal(got_depth, depth)
    assert np.nanmax(angular_error_deg(got_normal, normal, mask)) < 0.01
    assert np.all(got_normal[~mask] == 0)
    assert got_normal[20, 30, 0] > 0.5 and got_normal[5, 20, 1] > 0.5  # right side points right, top points up


def test_errors_name_the_file(tmp_path: Path) -> None:
    with pytest.raises(UserError, match=r"missing\.png: file does not exist"):
        read_normal_png(tmp_path / "missing.png")
    junk = tmp_path / "junk.png"
    junk.write_bytes(b"not an image")
    with pytest.raises(UserError, match=r"junk\.png: not a readable image"):
        read_normal_png(junk)
    gray = tmp_path / "gray.png"
    cv2.imwrite(str(gray), np.zeros((4, 4), np.uint8))
    with pytest.raises(UserError, match=r"gray\.png: expected a 3-channel RGB normal map"):
        read_normal_png(gray)
    with pytest.raises(UserError, match=r"folder .*nowhere does not exist"):
        write_normal_png(tmp_path / "nowhere" / "n.png", np.zeros((2, 2, 3)))
    with pytest.raises(UserError, match=r"depth_gt\.npz: file does not exist"):
        cv2.imwrite(str(tmp_path / "normal_map.png"), np.zeros((4, 4, 3), np.uint16))
        cv2.imwrite(str(tmp_path / "mask.png"), np.zeros((4, 4), np.uint8))
        read_geometry_folder(tmp_path)
