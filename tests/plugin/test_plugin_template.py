"""The example third-party plugin (examples/plugin-template), installed as a real distribution and
run end to end through ``pstoolkit run --solver flat``; the solver interface it builds on."""

from __future__ import annotations

import io
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from helpers import REPO

import psfmt
from pstoolkit.cli import main
from pstoolkit.cli.app import progress_bar
from pstoolkit.errors import UserError
from pstoolkit.optics.lights import build_light_model
from pstoolkit.plugin import manager as plugins
from pstoolkit.plugin.manager import get_registries
from pstoolkit.plugin.registry import PluginError
from pstoolkit.solve.base import SolverResult, check_inputs, resolve_device, run_solver
from pstoolkit.testing import install_project, sphere

TEMPLATE = REPO / "examples" / "plugin-template"
SIZE = 48
RADIUS_PX = 20.0


@pytest.fixture
def template(pstoolkit_plugins_alone: pytest.MonkeyPatch, tmp_path: Path) -> pytest.MonkeyPatch:
    """The template installed the way pip would: its dist-info (name, version and entry points read
    from its pyproject.toml) and its source folder on sys.path, loaded alone."""
    install_project(pstoolkit_plugins_alone, TEMPLATE, tmp_path / "site")
    return pstoolkit_plugins_alone


def sphere_capture(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """One frame of a white Lambertian sphere (albedo 0.8) under the template's static frontal light."""
    normal, mask = sphere(SIZE, RADIUS_PX)
    direction = np.array([0.0, 0.0, 1.0])
    image = 0.8 * np.clip(normal @ direction, 0.0, None)
    frames = psfmt.Frames(
        np.repeat(image[None, ..., None], 3, axis=-1).astype(np.float32),
        light_direction=direction[None],
        light_intensity=np.ones((1, 3)),
    )
    capture = psfmt.Capture(
        frames=frames,
        lights=psfmt.LightSpec("static", {"direction": direction, "intensity": np.ones(3)}),
        ground_truth=psfmt.GroundTruth(normal=normal, mask=mask),
        description="sphere under a static light",
    )
    psfmt.write(capture, path)
    return normal, mask


def test_flat_solver_runs_through_the_cli_with_known_error(
    template: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    capture, out = tmp_path / "sphere.h5", tmp_path / "out"
    normal_gt, mask = sphere_capture(capture)
    # The dimmest rim pixel is above the threshold, so the flat mask is the sphere's mask.
    assert 0.8 * normal_gt[mask, 2].min() > 0.01
    expected = np.degrees(np.arccos(normal_gt[mask, 2]))
    code = main(["run", str(capture), "--solver", "flat", "-o", str(out), "--set", "threshold=0.01", "--device", "cpu"])
    assert code == 0
    result = json.loads((out / "result.json").read_text())
    assert result["solver"] == "flat" and result["plugin"] == "template" and result["capture"] == str(capture)
    assert result["mae_deg"] == pytest.approx(expected.mean(), abs=1e-5)  # ground truth is stored as float32
    assert result["median_deg"] == pytest.approx(np.median(expected), abs=1e-5)
    assert 44.0 < result["mae_deg"] < 46.0  # a hemisphere seen from above: 45° in the continuum
    assert result["data_rate"] == pytest.approx(1 / 24)  # one RGB frame against 24
    assert result["options"] == {"threshold": 0.01, "min_events": 1}
    assert result["diagnostics"] == {"mask_pixels": int(mask.sum())}
    assert result["device"] == "cpu" and result["seconds"] >= 0.0
    normal = np.load(out / "normal.npy")
    assert normal.dtype == np.float32 and normal.shape == (SIZE, SIZE, 3)
    np.testing.assert_array_equal(normal[mask], np.tile([0.0, 0.0, 1.0], (int(mask.sum()), 1)))
    assert not normal[~mask].any()
    png = cv2.imread(str(out / "normal.png"), cv2.IMREAD_UNCHANGED)
    assert png.dtype == np.uint16 and png.shape == (SIZE, SIZE, 3)
    np.testing.assert_array_equal(png[mask], np.tile([65535, 32768, 32768], (int(mask.sum()), 1)))  # BGR: z, y, x
    assert not png[~mask].any()
    line = capsys.readouterr().out
    assert line == f"flat on {capture}: MAE {result['mae_deg']:.2f}°, median {result['median_deg']:.2f}°, coverage 100.0 %, " + (
        f"{result['seconds']:.2f} s, data rate 4.2 % → {out}\n"
    )


def test_run_json_prints_result_json(template: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    capture = tmp_path / "sphere.h5"
    sphere_capture(capture)
    template.chdir(tmp_path)
    assert main(["run", str(capture), "--solver", "flat", "--json", "--device", "cpu"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed == json.loads((tmp_path / "out" / "sphere-flat" / "result.json").read_text())
    assert printed["options"] == {"threshold": 0.05, "min_events": 1}


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--solver", "flat", "--set", "nope=1"], "solver 'flat' has no option 'nope' (options: min_events, threshold)"),
        (["--solver", "flat", "--set", "threshold=2"], "option threshold: 2.0 is above the maximum 1"),
        (["--solver", "flad"], "unknown solver 'flad' (known: flat)"),
        (["--solver", "flat", "--device", "gpu"], "--device 'gpu': expected one of auto, cpu, cuda"),
    ],
)
def test_run_rejects_bad_input_in_one_line(
    template: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], message: str
) -> None:
    capture = tmp_path / "sphere.h5"
    sphere_capture(capture)
    assert main(["run", str(capture), "-o", str(tmp_path / "out"), *args]) == 2
    assert capsys.readouterr().err == f"pstoolkit: error: {message}\n"
    assert not (tmp_path / "out").exists()


def test_run_with_a_missing_capture(template: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    missing = tmp_path / "missing.h5"
    assert main(["run", str(missing), "--solver", "flat", "--device", "cpu"]) == 2
    assert capsys.readouterr().err == f"pstoolkit: error: {missing}: no such file\n"


def test_template_is_listed_beside_core_without_clashes(template: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    template.setenv(plugins.ALLOW_ENV, "core,template")
    assert main(["plugins", "--json"]) == 0
    listing = {p["name"]: p for p in json.loads(capsys.readouterr().out)["plugins"]}
    mine = listing["template"]
    assert (mine["version"], mine["module"], mine["source"]) == ("0.1.0", "pstoolkit_template", "entry point")
    assert {kind: [e["name"] for e in entries] for kind, entries in mine["registered"].items()} == {
        "brdfs": ["blinn-phong"],
        "light_models": ["static"],
        "shadow_detectors": ["quiet"],
        "solvers": ["flat"],
    }
    assert get_registries().light_models.names() == ["near-ring", "ring", "sampled", "static"]


def test_static_light_model_is_found_through_the_registry(template: pytest.MonkeyPatch) -> None:
    light = build_light_model(psfmt.LightSpec("static", {"direction": [0.0, 3.0, 4.0], "intensity": [1.0, 0.5, 0.25]}))
    assert type(light).__module__ == "pstoolkit_template.static_light"
    direction, intensity = light.evaluate(np.array([0, 10, 20]))
    np.testing.assert_allclose(direction, np.tile([0.0, 0.6, 0.8], (3, 1)))
    np.testing.assert_array_equal(intensity, np.tile([1.0, 0.5, 0.25], (3, 1)))
    direction, _ = light.evaluate(np.array([0, 1]), points_mm=np.zeros((5, 3)))
    assert direction.shape == (2, 5, 3)
    again = build_light_model(light.to_spec())
    # normalised twice (the stored unit vector again): its norm is 1 only to rounding, which depends on
    # the CPU's dot-product kernel
    np.testing.assert_allclose(again.direction, light.direction, rtol=0, atol=1e-15)
    with pytest.raises(UserError, match=r"^light model 'static': parameter 'direction' is the zero vector$"):
        build_light_model(psfmt.LightSpec("static", {"direction": [0, 0, 0]}))


def test_the_template_detector_and_brdf_plug_into_dualres(template: pytest.MonkeyPatch, blobs_48: Path) -> None:
    """A third party's shadow detector and BRDF, found through its entry point, run inside dualres with
    their options from --set; the detector sees the blobs' shadows at the simulator's truth."""
    from pstoolkit.shadows.score import score, true_shadows
    from pstoolkit_dualres.preprocess import PreprocessOptions, preprocess

    template.setenv(plugins.ALLOW_ENV, "core,dualres,template")
    capture = psfmt.load(blobs_48)
    pre = preprocess(capture, PreprocessOptions())
    gt = capture.ground_truth
    entry = get_registries().shadow_detectors.get("quiet")
    assert entry.plugin == "template"
    mask = entry.obj().detect(pre.evidence, entry.parse_options(["silence_ms=3"]))
    precision, recall = score(mask, true_shadows(gt.depth, gt.mask, pre.light, pre.t0_us, pre.period_us), gt.mask)
    assert precision > 0.6 and recall > 0.3  # measured 0.71 / 0.41
    solver = get_registries().solvers.get("dualres")
    result, _ = run_solver(solver, capture, solver.parse_options(
        ["shadow_detector=quiet", "shadow.silence_ms=3", "brdf=blinn-phong", "epochs=20"]))
    assert result.diagnostics["shadow_detector"] == "quiet" and result.diagnostics["brdf"] == "blinn-phong"
    assert {"specular", "shininess", "albedo", "cast_shadow"} <= set(result.maps)
    assert result.maps["cast_shadow"][gt.mask].mean() > 0.01  # measured 0.025
    mae = float(np.degrees(np.arccos(np.clip(np.sum(result.normal * gt.normal, -1), -1, 1)))[gt.mask].mean())
    assert mae < 1.6  # measured 1.24° (frameps on the same frames: 2.15°)


def test_flat_mask_from_events_at_half_resolution(template: pytest.MonkeyPatch) -> None:
    """Events only, at 16×16 beside 32×32 ground truth: the mask comes from pixels that fired."""
    fired = np.zeros((16, 16), dtype=bool)
    fired[4:12, 5:9] = True
    fired[0, 0] = True
    y, x = np.nonzero(fired)
    x, y = np.repeat(x, 2), np.repeat(y, 2)  # two events per pixel …
    keep = ~((x == 0) & (y == 0)) | (np.arange(len(x)) % 2 == 0)  # … except one at (0, 0)
    x, y = x[keep], y[keep]
    t = np.arange(len(x), dtype=np.int64) * 10
    events = psfmt.Events(16, 16, psfmt.EventArray(x, y, t, np.ones(len(x))))
    gt = psfmt.GroundTruth(normal=np.dstack([np.zeros((32, 32, 2)), np.ones((32, 32))]), mask=np.ones((32, 32), bool))
    capture = psfmt.Capture(events=events, ground_truth=gt)
    entry = get_registries().solvers.get("flat")
    seen: list[float] = []
    result, _ = run_solver(entry, capture, entry.parse_options(["min_events=2"]), progress=lambda f, m: seen.append(f))
    expected = np.kron(fired, np.ones((2, 2), dtype=bool))
    expected[0:2, 0:2] = False
    np.testing.assert_array_equal(result.mask, expected)
    assert seen[-1] == 1.0
    result, _ = run_solver(entry, capture, entry.parse_options([]))
    np.testing.assert_array_equal(result.mask, np.kron(fired, np.ones((2, 2), dtype=bool)))


def test_flat_needs_frames_or_events(template: pytest.MonkeyPatch) -> None:
    entry = get_registries().solvers.get("flat")
    capture = psfmt.Capture(ground_truth=psfmt.GroundTruth(normal=np.zeros((4, 4, 3))))
    with pytest.raises(UserError, match=r"^solver 'flat' needs frames or events, but the capture has neither$"):
        run_solver(entry, capture, entry.parse_options([]))


class Broken:
    """A solver-shaped object that returns the wrong things, to check run_solver's guard."""

    name = "broken"
    summary = "returns whatever it is told to"
    needs = frozenset({"frames"})
    answer: object = None

    def __init__(self, device: str) -> None:
        self.device = device

    def solve(self, capture: psfmt.Capture, options: dict[str, object], progress: object) -> object:
        return Broken.answer


def test_run_solver_guards_against_bad_results_and_missing_inputs(monkeypatch: pytest.MonkeyPatch) -> None:
    from pstoolkit.plugin.registry import Registry

    registry = Registry("solver")
    with registry.registering_for("shoddy"):
        entry = registry.register(Broken)
    frames = psfmt.Frames(np.zeros((1, 4, 6, 3), dtype=np.float32))
    with pytest.raises(UserError, match=r"^solver 'broken' needs frames, but the capture has none \(events capture\)$"):
        check_inputs(entry, psfmt.Capture(events=psfmt.Events(6, 4, psfmt.EventArray.empty())))
    monkeypatch.setattr(Broken, "answer", {"normal": None})
    with pytest.raises(PluginError, match=r"^plugin 'shoddy': solver 'broken' returned dict, expected SolverResult$"):
        run_solver(entry, psfmt.Capture(frames=frames), {})
    monkeypatch.setattr(Broken, "answer", SolverResult(np.zeros((4, 4, 3)), np.zeros((4, 4))))
    with pytest.raises(PluginError, match=r"^plugin 'shoddy': solver 'broken' returned a \(4, 4\) normal map, expected \(4, 6\)$"):
        run_solver(entry, psfmt.Capture(frames=frames), {})
    monkeypatch.setattr(Broken, "needs", frozenset({"depth"}))
    with pytest.raises(PluginError, match=r"^plugin 'shoddy': solver 'broken' needs unknown input\(s\) depth$"):
        check_inputs(entry, psfmt.Capture(frames=frames))


def test_solver_result_checks_shapes() -> None:
    result = SolverResult(np.zeros((2, 3, 3), dtype=np.float64), np.ones((2, 3), dtype=np.uint8))
    assert result.normal.dtype == np.float32 and result.mask.dtype == bool
    with pytest.raises(ValueError, match=r"normal has shape \(2, 3\), expected \(H, W, 3\)"):
        SolverResult(np.zeros((2, 3)), np.ones((2, 3)))
    with pytest.raises(ValueError, match=r"mask has shape \(3, 2\), expected \(2, 3\)"):
        SolverResult(np.zeros((2, 3, 3)), np.ones((3, 2)))


def test_resolve_device(monkeypatch: pytest.MonkeyPatch) -> None:
    import torch

    assert resolve_device("cpu") == "cpu"
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("auto") == "cpu"
    with pytest.raises(UserError, match=r"^--device cuda: no CUDA GPU is available \(use --device cpu or auto\)$"):
        resolve_device("cuda")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert resolve_device("auto") == resolve_device("cuda") == "cuda"


def test_the_progress_bar_ends_once_at_100_percent_on_a_line_of_its_own() -> None:
    from rich.console import Console

    screen = io.StringIO()
    report = progress_bar("flat", console=Console(file=screen, force_terminal=True, width=80, color_system=None))
    report(0.5, "frames")
    report(0.504, "frames")
    report(1.2, "done")
    report(1.0, "done")  # the end reported twice: still one final line
    text = screen.getvalue()
    final = text.split("\r")[-1]
    assert "flat" in final and "100%" in final and "done" in final and final.endswith("\n\x1b[?25h")
    assert text.count("\n") == 1
