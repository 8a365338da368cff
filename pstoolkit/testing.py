"""Test helpers for plugin authors (and pstoolkit's own tests): entry points faked the way
``importlib.metadata`` reads them, an isolated plugin manager, and small generated captures.

In a plugin's ``conftest.py``::

    from pstoolkit.testing import pstoolkit_plugins, pstoolkit_plugins_alone  # noqa: F401

(or ``pytest_plugins = ["pstoolkit.testing"]`` in the top-level conftest of the run) gives the
fixtures ``pstoolkit_plugins`` (a clean plugin state with no plugin environment variables,
restored afterwards) and ``pstoolkit_plugins_alone`` (the same, with pstoolkit's built-in plugins
subject to ``PSTOOLKIT_PLUGINS`` like any other). Then, in a test::

    def test_my_solver(pstoolkit_plugins, tmp_path):
        install_project(pstoolkit_plugins, Path("."), tmp_path / "site", allow=["core", "mine"])
        capture = sphere_capture(tmp_path / "sphere.h5", lights=8)
        assert main(["run", str(capture), "--solver", "mine"]) == 0

Nothing here imports torch or numba.
"""

from __future__ import annotations

import sys
import textwrap
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
import pytest
import tomllib

import psfmt
from pstoolkit.plugin import manager

__all__ = ["fake_distribution", "install_project", "pstoolkit_plugins", "pstoolkit_plugins_alone", "sphere", "sphere_capture"]


def fake_distribution(
    root: Path, name: str, version: str, entry_points: dict[str, str], modules: dict[str, str] | None = None
) -> Path:
    """Lay out an installed distribution under ``root`` the way ``importlib.metadata`` reads it:
    ``<name>-<version>.dist-info`` with METADATA and ``entry_points.txt`` (group ``pstoolkit``), plus
    top-level modules ``modules`` (name → source, dedented). Put ``root`` on ``sys.path`` to install
    it. Returns ``root``."""
    info = root / f"{name.replace('-', '_')}-{version}.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: {version}\n")
    lines = "".join(f"{key} = {value}\n" for key, value in entry_points.items())
    (info / "entry_points.txt").write_text(f"[{manager.ENTRY_POINT_GROUP}]\n{lines}")
    for module, source in (modules or {}).items():
        (root / f"{module}.py").write_text(textwrap.dedent(source))
    return root


def install_project(
    monkeypatch: pytest.MonkeyPatch, project: Path, site: Path, allow: Sequence[str] | None = None
) -> list[str]:
    """Install the plugin project at ``project`` (a ``pyproject.toml`` with ``[project]`` name, version
    and ``pstoolkit`` entry points, sources in ``src/`` or beside it) as pip would for the duration of
    the test: its dist-info under ``site``, both on ``sys.path``. ``allow`` (default: the project's
    entry points) becomes ``PSTOOLKIT_PLUGINS``. Returns the project's plugin names."""
    meta = tomllib.loads((project / "pyproject.toml").read_text())["project"]
    points = meta.get("entry-points", {}).get(manager.ENTRY_POINT_GROUP, {})
    fake_distribution(site, meta["name"], meta["version"], points)
    monkeypatch.syspath_prepend(str(site))
    src = project / "src"
    monkeypatch.syspath_prepend(str(src if src.is_dir() else project))
    monkeypatch.setenv(manager.ALLOW_ENV, ",".join(allow if allow is not None else points))
    manager.reset()
    return list(points)


@pytest.fixture
def pstoolkit_plugins(monkeypatch: pytest.MonkeyPatch) -> Iterator[pytest.MonkeyPatch]:
    """A clean plugin state with no plugin environment variables (the built-in plugins load as
    always); afterwards the state is reset and the modules imported from paths the test added are
    forgotten."""
    yield from _isolated(monkeypatch)


@pytest.fixture
def pstoolkit_plugins_alone(monkeypatch: pytest.MonkeyPatch) -> Iterator[pytest.MonkeyPatch]:
    """``pstoolkit_plugins``, but pstoolkit's own plugins count as third parties, so that
    ``PSTOOLKIT_PLUGINS`` (``install_project``'s ``allow``) decides which of them load too: a test
    sees only the plugins it names."""
    monkeypatch.setattr(manager, "BUILT_IN_DISTRIBUTION", "")
    yield from _isolated(monkeypatch)


def _isolated(monkeypatch: pytest.MonkeyPatch) -> Iterator[pytest.MonkeyPatch]:
    monkeypatch.delenv(manager.DISABLE_ENV, raising=False)
    monkeypatch.delenv(manager.ALLOW_ENV, raising=False)
    modules, paths = set(sys.modules), set(sys.path)
    manager.reset()
    yield monkeypatch
    manager.reset()
    added = [Path(p) for p in set(sys.path) - paths if p]
    for name in set(sys.modules) - modules:
        origin = getattr(sys.modules[name], "__file__", None)
        if origin and any(Path(origin).is_relative_to(p) for p in added):
            del sys.modules[name]


def sphere(size: int, radius_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Normals (size, size, 3) float64, camera frame with y up, zero outside, and the mask
    (size, size) bool of a sphere of ``radius_px`` pixels centred in the image."""
    v, u = np.mgrid[0:size, 0:size].astype(np.float64)
    c = (size - 1) / 2.0
    x, y = (u - c) / radius_px, (c - v) / radius_px
    mask = x * x + y * y < 1.0
    normal = np.stack([x, y, np.sqrt(np.clip(1.0 - x * x - y * y, 0.0, None))], axis=-1)
    normal[~mask] = 0.0
    return normal, mask


def sphere_capture(path: Path, size: int = 48, lights: int = 8, albedo: float = 0.8, elevation_deg: float = 45.0) -> Path:
    """Write a classic capture of a Lambertian sphere (radius 0.42·size, grey ``albedo``) under
    ``lights`` directional lights evenly round a ring at ``elevation_deg`` above the image plane
    (``lights=1``: one frontal light), float32 frames, with ground-truth normals, mask and depth (the
    sphere's z towards the camera, one pixel = 1 mm). Returns ``path``."""
    radius = 0.42 * size
    normal, mask = sphere(size, radius)
    if lights == 1:
        directions = np.array([[0.0, 0.0, 1.0]])
    else:
        azimuth = 2 * np.pi * np.arange(lights) / lights
        elevation = np.radians(elevation_deg)
        directions = np.stack([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
                               np.full(lights, np.sin(elevation))], axis=-1)
    shading = albedo * np.clip(np.einsum("hwc,kc->khw", normal, directions), 0.0, None)
    frames = psfmt.Frames(
        np.repeat(shading[..., None], 3, axis=-1).astype(np.float32),
        light_direction=directions,
        light_intensity=np.ones((lights, 3)),
    )
    capture = psfmt.Capture(
        frames=frames,
        ground_truth=psfmt.GroundTruth(normal=normal.astype(np.float32), mask=mask,
                                       depth=np.where(mask, radius * normal[..., 2], 0.0).astype(np.float32)),
        description=f"Lambertian sphere under {lights} lights",
    )
    psfmt.write(capture, path)
    return path


def chrome_sphere_pinhole(
    k: np.ndarray, centre: np.ndarray, radius: float, light: np.ndarray, size: int, lobe_deg: float | None = 3.0
) -> np.ndarray:
    """A size×size image of a chrome sphere's highlight through a pinhole camera ``k`` (3, 3) (the
    conventions of ``psfmt.camera``): sphere ``centre`` (3,) and ``radius`` in mm, unit ``light``
    (3,) towards a distant light; 4×4 samples a pixel, each the ray's hit on the sphere, its normal
    and a Gaussian lobe of ``lobe_deg`` around the half vector (None: 1 wherever the ray hits, the
    sphere's coverage). A target for light calibrations independent of their own geometry."""
    offsets = (np.arange(4) + 0.5) / 4 - 0.5
    v, u = np.mgrid[0:size, 0:size].astype(np.float64)
    image = np.zeros((size, size))
    for du in offsets:
        for dv in offsets:
            x = (u + du - k[0, 2]) / k[0, 0]
            y = -(v + dv - k[1, 2]) / k[1, 1]
            d = np.stack([x, y, -np.ones_like(x)], axis=-1)
            d /= np.linalg.norm(d, axis=-1, keepdims=True)
            b = d @ centre
            disc = b * b - centre @ centre + radius * radius
            t = b - np.sqrt(np.clip(disc, 0, None))
            n = (t[..., None] * d - centre) / radius
            h = light - d
            h /= np.linalg.norm(h, axis=-1, keepdims=True)
            angle = np.arccos(np.clip(np.sum(n * h, axis=-1), -1, 1))
            lobe = 1.0 if lobe_deg is None else np.exp(-0.5 * (angle / np.radians(lobe_deg)) ** 2)
            image += np.where(disc > 0, lobe, 0.0)
    return image / 16
