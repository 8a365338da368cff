"""The template's own tests, written with ``pstoolkit.testing`` the way a plugin author would."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import psfmt
from pstoolkit import build_light_model, get_registries
from pstoolkit.cli import main
from pstoolkit.testing import install_project, sphere_capture

PROJECT = Path(__file__).resolve().parents[1]


@pytest.fixture
def template(pstoolkit_plugins: pytest.MonkeyPatch, tmp_path: Path) -> pytest.MonkeyPatch:
    install_project(pstoolkit_plugins, PROJECT, tmp_path / "site", allow=["core", "template"])
    return pstoolkit_plugins


def test_the_plugin_registers_its_four_entries(template: pytest.MonkeyPatch) -> None:
    registries = get_registries()
    assert registries.solvers.get("flat").plugin == "template"
    assert registries.light_models.get("static").plugin == "template"
    assert registries.shadow_detectors.get("quiet").plugin == "template"
    assert registries.brdfs.get("blinn-phong").plugin == "template"


def test_flat_solver_on_a_frontal_sphere(template: pytest.MonkeyPatch, tmp_path: Path) -> None:
    capture = sphere_capture(tmp_path / "sphere.h5", size=48, lights=1)
    out = tmp_path / "out"
    assert main(["run", str(capture), "--solver", "flat", "-o", str(out), "--set", "threshold=0.01", "--device", "cpu"]) == 0
    result = json.loads((out / "result.json").read_text())
    gt = psfmt.load(capture).ground_truth
    # a flat map (0, 0, 1) is off by the angle of each true normal from the view axis
    expected = np.degrees(np.arccos(np.clip(gt.normal[gt.mask, 2], -1.0, 1.0))).mean()
    assert result["plugin"] == "template" and result["mae_deg"] == pytest.approx(expected, abs=1e-4)


def test_the_static_light_round_trips(template: pytest.MonkeyPatch) -> None:
    light = build_light_model(psfmt.LightSpec("static", {"direction": [0.0, 3.0, 4.0], "intensity": [1.0, 1.0, 1.0]}))
    direction, intensity = light.evaluate(np.array([0, 5]))
    np.testing.assert_allclose(direction, [[0.0, 0.6, 0.8]] * 2)
    np.testing.assert_allclose(build_light_model(light.to_spec()).evaluate(np.array([0]))[0], direction[:1], atol=1e-12)
    assert intensity.shape == (2, 3)


def test_the_generated_sphere_is_exact_lambertian_data_for_frameps(template: pytest.MonkeyPatch, tmp_path: Path) -> None:
    capture = sphere_capture(tmp_path / "ring.h5", size=48, lights=8)
    out = tmp_path / "ring"
    template.setenv("PSTOOLKIT_PLUGINS", "core,frameps,template")
    assert main(["run", str(capture), "--solver", "frameps", "-o", str(out), "--device", "cpu"]) == 0
    result = json.loads((out / "result.json").read_text())
    # exact Lambertian data: least squares is exact wherever three or more lights reach the pixel; the
    # rim, lit by fewer, carries the mean (measured 4.9°)
    assert result["median_deg"] < 0.01 and result["mae_deg"] < 8.0 and result["coverage"] == 1.0
