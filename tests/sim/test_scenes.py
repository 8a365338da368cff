"""Scenes: geometry conventions, materials, determinism and the geometry-folder scene."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from pstoolkit.errors import UserError
from pstoolkit.plugin.manager import get_registries
from pstoolkit.plugin.options import defaults
from pstoolkit.sim.scenes import (
    SCENES,
    Blobs,
    Geometry,
    Relief,
    SceneMaps,
    Sphere,
    normals_from_height,
)


def build(cls: type, size: int = 32, seed: int = 0, **overrides: object) -> SceneMaps:
    return cls().build(size, seed, **{**defaults(cls.options), **overrides})


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=-1), -1.0, 1.0)))


def test_core_plugin_registers_every_scene() -> None:
    registry = get_registries().scenes
    assert [registry.get(cls.name).obj for cls in SCENES] == list(SCENES)


@pytest.mark.parametrize("cls", [Sphere, Blobs, Relief])
def test_maps_have_the_documented_shapes_units_and_background(cls: type) -> None:
    maps = build(cls, size=40)
    assert maps.normal.shape == (40, 40, 3) and maps.normal.dtype == np.float32
    assert maps.depth.shape == maps.mask.shape == maps.roughness.shape == (40, 40)
    assert maps.albedo.shape == maps.f0.shape == (40, 40, 3)
    norms = np.linalg.norm(maps.normal[maps.mask], axis=-1)
    np.testing.assert_allclose(norms, 1.0, atol=1e-5)
    assert np.all(maps.normal[maps.mask][:, 2] > 0)
    for array in (maps.normal, maps.depth, maps.albedo, maps.f0, maps.roughness):
        assert not np.any(array[~maps.mask])
    assert 0.0 < maps.albedo[maps.mask].min() and maps.albedo.max() <= 1.0


@pytest.mark.parametrize("cls", [Sphere, Blobs, Relief])
def test_normals_agree_with_the_depth_map(cls: type) -> None:
    """n ∝ (−∂h/∂x, −∂h/∂y, 1) with y up (rows down): the convention cast shadows and normals share."""
    maps = build(cls, size=64)
    inner = cv2.erode(maps.mask.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    if cls is Sphere:  # the rim is too steep for finite differences
        inner &= maps.normal[..., 2] > 0.5
    error = angle_deg(normals_from_height(maps.depth)[inner], maps.normal[inner])
    assert error.mean() < 1.5


def test_sphere_normals_are_exact_and_the_top_faces_up() -> None:
    maps = build(Sphere, size=33, radius=0.9)
    r = 0.9 * 33 / 2
    assert np.allclose(maps.normal[16, 16], [0.0, 0.0, 1.0], atol=1e-6)
    top = np.flatnonzero(maps.mask[:, 16])[0]
    assert maps.normal[top, 16, 1] > 0.9  # row 0 is the top of the image, so +y
    right = np.flatnonzero(maps.mask[16])[-1]
    assert maps.normal[16, right, 0] > 0.9
    np.testing.assert_allclose(maps.depth[16, 16], r, rtol=1e-6)
    assert maps.mask.sum() == pytest.approx(np.pi * r * r, rel=0.05)


def test_same_seed_same_scene_other_seed_other_scene() -> None:
    a, b, c = build(Blobs, seed=3), build(Blobs, seed=3), build(Blobs, seed=4)
    for key in ("normal", "depth", "albedo"):
        # bit-equal: the same seed through the same code in the same process
        assert np.array_equal(getattr(a, key), getattr(b, key))
    assert not np.array_equal(a.depth, c.depth)


def test_texture_pattern_is_the_same_at_every_size() -> None:
    small = build(Blobs, size=32, albedo="texture").albedo  # blobs fill the frame
    large = build(Blobs, size=64, albedo="texture").albedo
    shrunk = cv2.resize(large, (32, 32), interpolation=cv2.INTER_AREA)
    assert np.abs(shrunk - small).max() < 0.03


def test_metallic_moves_the_colour_from_albedo_to_f0() -> None:
    plain = build(Sphere, albedo="texture", f0=0.04)
    metal = build(Sphere, albedo="texture", f0=0.04, metallic=1.0)
    half = build(Sphere, albedo="texture", f0=0.04, metallic=0.5)
    inside = plain.mask
    assert not np.any(metal.albedo)
    np.testing.assert_allclose(metal.f0[inside], plain.albedo[inside], atol=1e-6)
    np.testing.assert_allclose(half.albedo[inside], 0.5 * plain.albedo[inside], atol=1e-6)
    np.testing.assert_allclose(half.f0[inside], 0.5 * 0.04 + 0.5 * plain.albedo[inside], atol=1e-6)
    assert np.all(metal.metallic[inside] == 1.0)


def test_varying_materials_stay_within_half_and_one_and_a_half_times() -> None:
    maps = build(Relief, f0=0.2, roughness=0.4, varying=True)
    inside = maps.mask
    f0, rough = maps.f0[inside][:, 0], maps.roughness[inside]
    assert 0.1 - 1e-6 <= f0.min() < f0.max() <= 0.3 + 1e-6
    assert 0.2 - 1e-6 <= rough.min() < rough.max() <= 0.6 + 1e-6
    assert np.ptp(f0) > 0.02


def _write_geometry_folder(folder: Path, size: int = 40, radius_px: float = 14.0, focal_px: float = 1000.0,
                           distance_mm: float = 500.0) -> None:
    """A sphere seen by a camera at ``distance_mm``: one pixel spans distance/focal mm."""
    folder.mkdir()
    v, u = np.mgrid[0:size, 0:size].astype(np.float64)
    c = (size - 1) / 2.0
    x, y = (u - c) / radius_px, (c - v) / radius_px
    mask = x * x + y * y < 1.0
    z = np.sqrt(np.clip(1.0 - x * x - y * y, 0.0, None))
    normal = np.stack([x, y, z], axis=-1) * mask[..., None]
    encoded = np.where(mask[..., None], np.round((normal + 1.0) / 2.0 * 65535), 65535).astype(np.uint16)
    cv2.imwrite(str(folder / "normal_map.png"), encoded[..., ::-1])
    cv2.imwrite(str(folder / "mask.png"), (mask * 255).astype(np.uint8))
    mm_per_px = distance_mm / focal_px
    depth = np.where(mask, distance_mm - z * radius_px * mm_per_px, 0.0)
    np.savez(folder / "depth_gt.npz", depth_gt=depth)
    np.savetxt(folder / "K.txt", np.array([[focal_px, 0, c], [0, focal_px, c], [0, 0, 1]]))


def test_geometry_folder_becomes_a_scene_in_pixel_units(tmp_path: Path) -> None:
    _write_geometry_folder(tmp_path / "ball")
    maps = build(Geometry, size=32, source=str(tmp_path / "ball"))
    reference = build(Sphere, size=32, radius=1.0 / 1.16)  # the crop keeps an 8 % margin per side
    both = maps.mask & reference.mask & (reference.normal[..., 2] > 0.3)
    assert angle_deg(maps.normal[both], reference.normal[both]).mean() < 3.0
    # the depth range is the sphere's radius, rescaled like the image (28 px across → 32·28/side)
    side = int(np.ceil(28 * 1.16))
    radius_out = 14.0 * 32 / side
    assert np.ptp(maps.depth[maps.mask]) == pytest.approx(radius_out, rel=0.08)
    inner = cv2.erode(maps.mask.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    assert angle_deg(normals_from_height(maps.depth)[inner], maps.normal[inner]).mean() < 4.0


def test_geometry_errors_name_the_missing_piece(tmp_path: Path) -> None:
    with pytest.raises(UserError, match=r"needs a source folder \(--source DIR\)"):
        build(Geometry)
    _write_geometry_folder(tmp_path / "ball")
    (tmp_path / "ball" / "K.txt").unlink()
    with pytest.raises(UserError, match=r"K\.txt: file does not exist"):
        build(Geometry, source=str(tmp_path / "ball"))
