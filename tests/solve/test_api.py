"""The Python API (issue 24, part C, item 1): ``pstoolkit.solve_capture(capture, "frameps", robust=True)``
with options checked as ``--set`` checks them, the ``Solution`` it returns, solvers that take a
partial options dict, and the README's "Python API" block, run as written."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import REPO

import psfmt
import pstoolkit
from pstoolkit import Solution, SolverResult, UserError, get_registries
from pstoolkit.solve.api import assignments
from pstoolkit.solve.base import run_solver
from pstoolkit.testing import sphere_capture


@pytest.fixture(scope="module")
def sphere(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return sphere_capture(tmp_path_factory.mktemp("api") / "sphere.h5")


def _python_api_block() -> str:
    """The python code block of the README's "Python API" section."""
    section = (REPO / "README.md").read_text(encoding="utf-8").split("\n## Python API\n", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```python\n(.*?)```", section, flags=re.S)
    assert len(blocks) == 1, "the Python API section holds one python block"
    return blocks[0]


def test_the_readme_python_api_block_runs_as_written(sphere: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / "sphere.h5").write_bytes(sphere.read_bytes())
    monkeypatch.chdir(tmp_path)
    namespace: dict[str, object] = {}
    exec(compile(_python_api_block(), "README.md: Python API", "exec"), namespace)
    result = namespace["result"]
    assert isinstance(result, Solution) and isinstance(result, SolverResult)
    assert result.solver == "frameps" and result.options["robust"] is True and result.options["frames"] == 0
    assert namespace["mae"] == result.score.stats["mae_deg"] < 5.0
    assert namespace["surface"].depth.shape == namespace["steps"].depth.shape == (48, 48)
    summary = json.loads((tmp_path / "out" / "sphere-frameps" / "result.json").read_text())
    assert (summary["solver"], summary["object"], summary["options"]["robust"]) == ("frameps", "sphere", True)
    assert summary["mae_deg"] == pytest.approx(result.score.stats["mae_deg"])
    assert summary["capture"] == str(tmp_path / "sphere.h5")
    assert {"normal.npy", "normal.png", "error.npy", "albedo.npy"} <= {p.name for p in (tmp_path / "out" / "sphere-frameps").iterdir()}


def test_solve_takes_a_path_or_a_capture_and_matches_a_run_with_the_same_options(sphere: Path) -> None:
    entry = get_registries().solvers.get("frameps")
    expected, _ = run_solver(entry, psfmt.load(sphere), entry.parse_options(["frames=4", "robust=true"]))
    by_path = pstoolkit.solve_capture(sphere, "frameps", device="cpu", frames=4, robust=True)
    with psfmt.read(sphere) as capture:
        seen: list[float] = []
        by_capture = pstoolkit.solve_capture(capture, "frameps", device="cpu", frames=4, robust=True, progress=lambda f, m: seen.append(f))
    for solution in (by_path, by_capture):
        np.testing.assert_array_equal(solution.normal, np.where(expected.mask[..., None], expected.normal, 0))
        np.testing.assert_array_equal(solution.mask, expected.mask)
        assert solution.options == entry.parse_options(["frames=4", "robust=true"])
        assert solution.device == "cpu" and solution.seconds > 0 and solution.capture_kind == "frames"
        assert solution.data_rate == pytest.approx(4 * 48 * 48 * 3 / (24 * 48 * 48 * 3))
    assert by_path.capture_path == sphere.absolute() and seen and seen[-1] == 1.0
    text = repr(by_path)
    assert len(text) < 200 and text.startswith("Solution('frameps', 48×48, MAE ") and "maps: albedo" in text


@pytest.mark.parametrize(("keywords", "pairs"), [
    ({"frames": -1}, ["frames=-1"]),
    ({"frames": "six"}, ["frames=six"]),
    ({"frames": 2.5}, ["frames=2.5"]),
    ({"robust": "maybe"}, ["robust=maybe"]),
    ({"robustly": True}, ["robustly=true"]),
    ({"dark_fraction": float("nan")}, ["dark_fraction=nan"]),
])
def test_bad_options_raise_the_error_set_raises(sphere: Path, keywords: dict[str, object], pairs: list[str]) -> None:
    with pytest.raises(UserError) as from_set:
        get_registries().solvers.get("frameps").parse_options(pairs)
    with pytest.raises(UserError) as from_python:
        pstoolkit.solve_capture(sphere, "frameps", device="cpu", **keywords)
    assert str(from_python.value) == str(from_set.value)


def test_unknown_solver_and_bad_capture_are_clear_errors(sphere: Path) -> None:
    with pytest.raises(UserError, match=r"^unknown solver 'nope' \(known: .*frameps"):
        pstoolkit.solve_capture(sphere, "nope")
    with pytest.raises(TypeError, match="capture must be a psfmt.Capture or the path of a capture file, not int"):
        pstoolkit.solve_capture(3, "frameps", device="cpu")  # type: ignore[arg-type]
    with pytest.raises(UserError, match=r"^solver 'eventps' needs events and lights, but .*sphere.h5 has none \(frames capture\)$"):
        pstoolkit.solve_capture(sphere, "eventps", device="cpu")


def test_multiple_and_nested_options_become_set_assignments() -> None:
    dualres = get_registries().solvers.get("dualres")
    pairs = assignments(dualres, {"epochs": 3, "lr": 0.01, "shadow": {"min_gap_ms": 0.5}, "shadow_detector": "silences",
                                  "seed": np.int64(2)})
    assert pairs == ["epochs=3", "lr=0.01", "shadow.min_gap_ms=0.5", "shadow_detector=silences", "seed=2"]
    parsed = dualres.parse_options(pairs)
    assert (parsed["epochs"], parsed["shadow"], parsed["seed"]) == (3, ("min_gap_ms=0.5",), 2)
    assert assignments(dualres, {"shadow": ["min_gap_ms=0.5", "ratio=2"]}) == ["shadow.min_gap_ms=0.5", "shadow.ratio=2"]
    assert assignments(dualres, {"shadow.ratio": 2.0}) == ["shadow.ratio=2.0"]
    diligent = get_registries().converters.get("diligent")
    assert diligent.parse_options(assignments(diligent, {"object": ["ball", "cat"]}))["object"] == ("ball", "cat")


def test_a_solver_takes_a_partial_options_dict(sphere: Path) -> None:
    """Issue 24: ``FramePS().solve(capture, {"robust": True})`` failed with KeyError 'frames'; the
    options left out take their defaults, in ``solve`` and in ``run_solver``."""
    entry = get_registries().solvers.get("frameps")
    capture = psfmt.load(sphere)
    full, _ = run_solver(entry, capture, entry.parse_options(["robust=true"]))
    partial = entry.obj().solve(capture, {"robust": True})
    through_run, _ = run_solver(entry, capture, {"robust": True})
    for result in (partial, through_run):
        np.testing.assert_array_equal(result.normal, full.normal)
    np.testing.assert_array_equal(entry.obj().solve(capture).normal, run_solver(entry, capture, {})[0].normal)
    with pytest.raises(UserError, match=r"^solver 'frameps' has no option 'robustly' \(options: dark_fraction, frames, robust"):
        run_solver(entry, capture, {"robustly": True})
    with pytest.raises(UserError, match=r"^solver 'frameps' has no option 'robustly'"):
        entry.obj().solve(capture, {"robustly": True})


def test_writing_needs_a_capture_file_and_a_positive_error_scale(sphere: Path, tmp_path: Path) -> None:
    in_memory = psfmt.load(sphere)
    in_memory.path = None
    solution = pstoolkit.solve_capture(in_memory, "frameps", device="cpu")
    assert solution.capture_path is None and solution.score is not None
    with pytest.raises(UserError, match="made in memory"):
        solution.write(tmp_path / "r")
    solved = pstoolkit.solve_capture(sphere, "frameps", device="cpu")
    with pytest.raises(UserError, match=r"error_max_deg 0: expected a number of degrees above 0 and at most 180"):
        solved.write(tmp_path / "r", error_max_deg=0)
    out = solved.write(tmp_path / "r", name="mine", obj="ball", error_max_deg=10.0)
    summary = json.loads((out / "result.json").read_text())
    assert (summary["name"], summary["object"], summary["error_max_deg"]) == ("mine", "ball", 10.0)
    assert not (tmp_path / "r2").exists()


def test_the_api_function_and_the_solve_package_each_mean_one_thing() -> None:
    """``pstoolkit.solve_capture`` is the function of the API and ``pstoolkit.solve`` the plain
    subpackage of the solver interface, in a fresh interpreter, and no torch loads."""
    code = (
        "import sys, types\n"
        "import pstoolkit.solve.results as results\n"
        "import pstoolkit\n"
        "from pstoolkit.solve import base\n"
        "from pstoolkit import solve, solve_capture\n"
        "assert type(solve) is types.ModuleType and not callable(solve)\n"
        "assert solve_capture is pstoolkit.solve.api.solve_capture\n"
        "assert pstoolkit.solve.base.run_solver is base.run_solver and results.__name__ == 'pstoolkit.solve.results'\n"
        "print(sorted({'torch', 'numba', 'matplotlib'} & set(sys.modules)))\n"
    )
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env).stdout
    assert out.strip() == "[]"
    assert "solve_capture" in pstoolkit.__all__ and "Solution" in pstoolkit.__all__
