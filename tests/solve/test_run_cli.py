"""``pstoolkit run``: every output file, the error map, --store, --json, the demo capture and bad input.

The solver is a small real one installed as a plugin distribution: Woodham's least squares on a
simulated Lambertian sphere under 8 instantaneous ring lights, which also returns an RGB albedo, a
grey residual and a per-light shading stack (a map that is not an image).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import sys
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest
from helpers.solvers import LIGHTS, SIZE, lsq_plugin, simulate_sphere

import psfmt
import pstoolkit
from pstoolkit.cli import main
from pstoolkit.evaluation.metrics import angular_error_deg
from pstoolkit.sim import demo


@pytest.fixture
def lsq(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> Iterator[pytest.MonkeyPatch]:
    with lsq_plugin(monkeypatch, tmp_path):
        yield monkeypatch


@pytest.fixture
def sphere(lsq: pytest.MonkeyPatch, tmp_path: Path) -> Path:
    return simulate_sphere(tmp_path / "sphere.h5")


def run(capture: Path | None, out: Path | None, *args: str) -> int:
    where = [str(capture)] if capture is not None else []
    to = ["-o", str(out)] if out is not None else []
    return main(["run", *where, "--solver", "lsq", *to, "--device", "cpu", *args])


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_run_writes_every_map_and_a_consistent_error_map(
    sphere: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    before = digest(sphere)
    assert run(sphere, out) == 0
    assert digest(sphere) == before  # without --store the capture is not touched
    with psfmt.read(sphere) as capture:
        gt = capture.ground_truth
    inside = gt.mask
    result = json.loads((out / "result.json").read_text())
    normal = np.load(out / "normal.npy")
    assert normal.dtype == np.float32 and normal.shape == (SIZE, SIZE, 3)

    error = np.load(out / "error.npy")
    expected = angular_error_deg(normal, gt.normal, inside)
    assert error.dtype == np.float32 and error.shape == (SIZE, SIZE)
    np.testing.assert_array_equal(np.isnan(error), ~inside)
    np.testing.assert_allclose(error[inside], expected[inside], rtol=0, atol=1e-4)
    assert result["mae_deg"] == pytest.approx(float(np.mean(expected[inside])), abs=1e-9)
    assert result["median_deg"] == pytest.approx(float(np.median(expected[inside])), abs=1e-9)
    for threshold, key in ((11.25, "below_11_25"), (22.5, "below_22_5"), (30, "below_30")):
        share = np.count_nonzero(expected[inside] < threshold) / inside.sum()
        assert result[key] == pytest.approx(share)
    assert result["n_pixels"] == int(inside.sum())
    assert result["coverage"] == 1.0 and result["mae_solved_deg"] == pytest.approx(result["mae_deg"])
    # Least squares is exact where all 8 lights see a pixel; the rim (attached shadows) drags the mean.
    assert result["median_deg"] < 1.0 and 3.0 < result["mae_deg"] < 8.0

    assert {k: result[k] for k in ("name", "solver", "plugin", "object", "capture", "capture_kind", "size")} == {
        "name": "lsq",
        "solver": "lsq",
        "plugin": "lsq",
        "object": "sphere",
        "capture": str(sphere),
        "capture_kind": "frames",
        "size": [SIZE, SIZE],
    }
    assert result["data_rate"] == pytest.approx(LIGHTS / 24)
    assert result["options"] == {"threshold": 0.02}
    assert result["pstoolkit_version"] == pstoolkit.__version__
    assert result["error_max_deg"] == 30.0 and result["stored"] is None and result["seconds"] >= 0.0

    png = cv2.imread(str(out / "error.png"), cv2.IMREAD_UNCHANGED)[..., ::-1]
    assert png.dtype == np.uint8 and png.shape == (SIZE, SIZE, 3)
    assert not png[~inside].any()
    level = np.clip(error[inside] / 30.0 * 255.0 + 0.5, 0, 255).astype(np.uint8)
    turbo = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], cv2.COLORMAP_TURBO)[:, 0, ::-1]
    np.testing.assert_array_equal(png[inside], turbo[level])

    mask = np.any(normal != 0, axis=-1)
    albedo = np.load(out / "albedo.npy")
    assert albedo.dtype == np.float32 and albedo.shape == (SIZE, SIZE, 3)
    scale = result["maps"]["albedo"]["scale"]
    assert scale == pytest.approx(np.percentile(albedo[mask].astype(np.float64), 99.0))
    albedo_png = cv2.imread(str(out / "albedo.png"), cv2.IMREAD_UNCHANGED)[..., ::-1]
    assert albedo_png.dtype == np.uint16 and albedo_png.shape == (SIZE, SIZE, 3)
    assert not albedo_png[~mask].any()
    decoded = albedo_png[mask] / 65535.0 * scale
    np.testing.assert_allclose(decoded, np.minimum(albedo[mask], scale), atol=0.5 / 65535 * scale + 1e-7)

    residual = np.load(out / "residual.npy")
    residual_png = cv2.imread(str(out / "residual.png"), cv2.IMREAD_UNCHANGED)
    assert residual.shape == residual_png.shape == (SIZE, SIZE) and residual_png.dtype == np.uint16
    assert result["maps"]["residual"]["scale"] == 1.0  # a grey map within [0, 1] keeps its values
    # integers from the same float64 expression (value / 1.0 · 65535 + 0.5, floored) as outputs.encode_map
    np.testing.assert_array_equal(residual_png[mask], np.floor(residual[mask].astype(np.float64) * 65535 + 0.5))

    shading = np.load(out / "shading.npy")
    assert shading.dtype == np.float32 and shading.shape == (LIGHTS, SIZE, SIZE)
    assert not (out / "shading.png").exists()
    assert result["maps"]["shading"] == {"npy": "shading.npy", "shape": [LIGHTS, SIZE, SIZE]}
    assert sorted(p.name for p in out.iterdir()) == sorted(
        ["albedo.npy", "albedo.png", "error.npy", "error.png", "normal.npy", "normal.png"]
        + ["residual.npy", "residual.png", "result.json", "shading.npy"]
    )
    captured = capsys.readouterr()
    assert captured.out == (
        f"lsq on {sphere}: MAE {result['mae_deg']:.2f}°, median {result['median_deg']:.2f}°, coverage 100.0 %, "
        f"{result['seconds']:.2f} s, data rate 33.3 % → {out}\n"
    )
    assert captured.err == ""



def test_unsolved_pixels_count_90_degrees_but_are_drawn_grey(sphere: Path, tmp_path: Path) -> None:
    """With a high mask threshold the solver leaves the dim rim out: those pixels count 90° in mae_deg
    and error.npy, the coverage and mae_solved_deg say so, and error.png draws them neutral grey."""
    out = tmp_path / "hi"
    assert run(sphere, out, "--set", "threshold=0.5") == 0
    result = json.loads((out / "result.json").read_text())
    with psfmt.read(sphere) as capture:
        gt = capture.ground_truth
    normal, error = np.load(out / "normal.npy"), np.load(out / "error.npy")
    unsolved = gt.mask & ~np.any(normal != 0, axis=-1)
    assert 0.1 < unsolved.sum() / gt.mask.sum() < 0.9
    np.testing.assert_array_equal(error[unsolved], 90.0)
    assert result["coverage"] == pytest.approx(1.0 - unsolved.sum() / gt.mask.sum())
    assert result["mae_deg"] == pytest.approx(float(np.mean(error[gt.mask])), abs=1e-4)
    assert result["mae_solved_deg"] == pytest.approx(float(np.mean(error[gt.mask & ~unsolved])), abs=1e-4)
    rgb = cv2.imread(str(out / "error.png"))[..., ::-1]
    np.testing.assert_array_equal(rgb[unsolved], np.tile([128, 128, 128], (int(unsolved.sum()), 1)))
    np.testing.assert_array_equal(rgb[~gt.mask], 0)
    solved = gt.mask & ~unsolved
    assert not np.any(np.all(rgb[solved] == 128, axis=-1))  # Turbo has no neutral grey

def test_error_max_sets_the_top_of_the_colour_scale(sphere: Path, tmp_path: Path) -> None:
    assert run(sphere, tmp_path / "out", "--error-max", "5") == 0
    error = np.load(tmp_path / "out" / "error.npy")
    png = cv2.imread(str(tmp_path / "out" / "error.png"), cv2.IMREAD_UNCHANGED)[..., ::-1]
    turbo_top = cv2.applyColorMap(np.array([[255]], dtype=np.uint8), cv2.COLORMAP_TURBO)[0, 0, ::-1]
    over = error >= 5.0
    assert over.any()
    np.testing.assert_array_equal(png[over], np.tile(turbo_top, (int(over.sum()), 1)))
    assert json.loads((tmp_path / "out" / "result.json").read_text())["error_max_deg"] == 5.0


def test_json_prints_result_json_and_no_progress_even_on_a_terminal(
    sphere: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], lsq: pytest.MonkeyPatch
) -> None:
    lsq.setattr(sys.stderr, "isatty", lambda: True)
    assert run(sphere, tmp_path / "out", "--json") == 0
    captured = capsys.readouterr()
    assert json.loads(captured.out) == json.loads((tmp_path / "out" / "result.json").read_text())
    assert captured.err == ""
    assert run(sphere, tmp_path / "out") == 0
    final = capsys.readouterr().err.split("\r")[-1]  # the bar's last state, left on screen
    assert "lsq" in final and "100%" in final and "solved" in final


def test_store_round_trips_through_the_capture(sphere: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    with psfmt.read(sphere) as capture:
        frames = capture.frames.as_float()
    assert run(sphere, out, "--store", "--name", "lsq-test", "--set", "threshold=0.03") == 0
    assert capsys.readouterr().err == f"stored result 'lsq-test' in {sphere}\n"
    summary = json.loads((out / "result.json").read_text())
    assert summary["name"] == summary["stored"] == "lsq-test"
    with psfmt.read(sphere) as capture:
        # bit-equal: the same stored frames through the same conversion
        np.testing.assert_array_equal(capture.frames.as_float(), frames)
        assert list(capture.results) == ["lsq-test"]
    stored = psfmt.load(sphere).results["lsq-test"]  # read lazily, a stored result's maps need the file open
    assert (stored.solver, stored.version, stored.options) == ("lsq", pstoolkit.__version__, {"threshold": 0.03})
    assert stored.seconds == summary["seconds"]
    assert sorted(stored.maps) == ["albedo", "mask", "normal", "residual", "shading"]
    normal = np.load(out / "normal.npy")
    # bit-equal: the same float32 arrays, stored in the capture and in the .npy files
    np.testing.assert_array_equal(stored.maps["normal"], normal)
    np.testing.assert_array_equal(stored.maps["mask"].astype(bool), np.any(normal != 0, axis=-1))
    for name in ("albedo", "residual", "shading"):
        np.testing.assert_array_equal(stored.maps[name], np.load(out / f"{name}.npy"))
    report = psfmt.validate(sphere)
    assert report.valid, report.errors


def test_no_capture_runs_on_the_demo_in_the_cache(
    lsq: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # The real demo is a 128-pixel hybrid capture; a tiny classic one keeps the test fast and fits lsq.
    tiny = dataclasses.replace(demo.DEMO_CONFIG, scene="sphere", size=SIZE, discrete_lights=LIGHTS, brdf="lambertian")
    lsq.setattr(demo, "DEMO_CONFIG", tiny)
    lsq.chdir(tmp_path)
    assert run(None, None, "--json") == 0
    captured = capsys.readouterr()
    assert captured.err == "no CAPTURE given: running on the built-in demo capture (simulated on first use, then cached)\n"
    result = json.loads(captured.out)
    cached = tmp_path / "cache" / "pstoolkit" / f"demo-{demo.demo_key(tiny)}.h5"
    assert result["capture"] == str(cached) and result["object"] == "demo"
    assert (tmp_path / "out" / "demo-lsq" / "normal.npy").is_file()
    before = digest(cached)
    assert run(None, tmp_path / "again") == 0  # the cached file is reused as it is
    assert digest(cached) == before
    capsys.readouterr()
    assert run(None, tmp_path / "stored", "--store") == 0
    assert capsys.readouterr().err.endswith(
        f"stored result 'lsq' in the demo capture {cached} (a cached file, regenerated without it if the cache is cleared)\n"
    )
    with psfmt.read(cached) as capture:
        assert list(capture.results) == ["lsq"]


def events_only(path: Path) -> None:
    x = np.arange(16) % 8
    events = psfmt.Events(8, 8, psfmt.EventArray(x, x, np.arange(16, dtype=np.int64) * 10, np.ones(16)))
    psfmt.write(psfmt.Capture(events=events), path)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--solver", "lsqq"], "unknown solver 'lsqq' (known: badmap, evlsq, lsq)"),
        (["--solver", "lsq", "--set", "level=1"], "solver 'lsq' has no option 'level' (options: threshold)"),
        (["--solver", "lsq", "--set", "threshold=-1"], "option threshold: -1.0 is below the minimum 0"),
        (["--solver", "lsq", "--error-max", "0"], "--error-max 0: expected a number of degrees above 0 and at most 180"),
        (["--solver", "lsq", "--name", "a/b"], "--name 'a/b': use letters, digits, '.', '_' and '-', starting with a letter or digit"),
        (["--solver", "evlsq"], "solver 'evlsq' needs events, but {capture} has none (frames capture)"),
        (["--solver", "badmap"], "plugin 'lsq': solver 'badmap' returned a map named 'error': names are letters, digits, '_' and '-', not error, mask, normal"),
    ],
)
def test_bad_input_is_one_line_exit_2_and_writes_nothing(
    sphere: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], message: str
) -> None:
    before = digest(sphere)
    assert main(["run", str(sphere), "-o", str(tmp_path / "out"), "--device", "cpu", "--store", *args]) == 2
    assert capsys.readouterr().err == f"pstoolkit: error: {message.format(capture=sphere)}\n"
    assert not (tmp_path / "out").exists()
    assert digest(sphere) == before


def test_missing_capture_and_one_lacking_frames(lsq: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    missing = tmp_path / "missing.h5"
    assert run(missing, tmp_path / "out") == 2
    assert capsys.readouterr().err == f"pstoolkit: error: {missing}: no such file\n"
    events = tmp_path / "events.h5"
    events_only(events)
    assert run(events, tmp_path / "out") == 2
    assert capsys.readouterr().err == f"pstoolkit: error: solver 'lsq' needs frames, but {events} has none (events capture)\n"
    assert not (tmp_path / "out").exists()


def test_data_rate_counts_only_what_the_solver_read(tmp_path: Path) -> None:
    """On one hybrid capture, frameps is charged for its frames, eventps for the events, and
    frameps with frames=K for K frames — the paper's per-method accounting."""
    capture = tmp_path / "hybrid.h5"
    assert main(["simulate", "sphere", "-o", str(capture), "--size", "32", "--frames", "6", "--brdf", "lambertian", "--quiet"]) == 0
    with psfmt.read(capture) as data:
        n_events = len(data.events)
    reference = 24 * 32 * 32 * 3
    frame = 32 * 32 * 3
    expected = {
        ("frameps",): 6 * frame / reference,
        ("frameps", "--set", "frames=3"): 3 * frame / reference,
        ("eventps",): 2 * n_events / reference,
    }
    for args, rate in expected.items():
        out = tmp_path / "-".join(args).replace("=", "")
        assert main(["run", str(capture), "--solver", *args, "-o", str(out), "--device", "cpu", "--json"]) == 0
        assert json.loads((out / "result.json").read_text())["data_rate"] == pytest.approx(rate, rel=1e-12)
    assert psfmt.data_rate(psfmt.load(capture), frames=1, events=False).rate == pytest.approx(frame / reference)
