"""Reproducible runs (issue 24, part B): ``--config FILE`` for ``run`` and ``batch`` (a TOML file, or an
earlier run's result.json), result.json recording what a repeat needs (options as resolved, the
capture's absolute path and SHA-256, the toolkit's version), and ``run -o DIR`` replacing the result
folder as a unit.

Captures: a 32 px Lambertian sphere under 8 instantaneous lights (frameps) and a 32 px hybrid capture
(dualres for the maps frameps does not write)."""

from __future__ import annotations

import hashlib
import json
import shutil
import textwrap
from pathlib import Path

import numpy as np
import pytest
from helpers.solvers import simulate_sphere

import psfmt
import pstoolkit
from pstoolkit.cli import main
from pstoolkit.plugin.manager import get_registries
from pstoolkit.sim.config import SimulationConfig
from pstoolkit.sim.simulator import simulate
from pstoolkit.solve.config import read_config

FRAMEPS_DEFAULTS = {"frames": 0, "robust": False, "dark_fraction": 0.25, "saturation_level": 1.0, "threshold": 0.002}
FRAMEPS_FILES = ["albedo.npy", "albedo.png", "error.npy", "error.png", "normal.npy", "normal.png", "result.json"]


@pytest.fixture(scope="module")
def classic(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return simulate_sphere(tmp_path_factory.mktemp("classic") / "sphere.h5")


@pytest.fixture(scope="module")
def hybrid(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("hybrid") / "hybrid.h5"
    simulate(SimulationConfig(scene="sphere", size=32, brdf="lambertian"), path)
    return path


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(textwrap.dedent(text).lstrip())
    return path


def result(folder: Path) -> dict:
    return json.loads((folder / "result.json").read_text())


def run(*args: str) -> int:
    return main(["run", *args, "--device", "cpu", "--json"])


def test_a_toml_file_gives_the_solver_its_options_and_the_flags(
    classic: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Paths are relative to the file's folder, not to the working folder; ``set`` and ``[options]``
    are checked like --set and both apply."""
    folder = tmp_path / "project"
    shutil.copy(classic, tmp_path / "sphere.h5")
    config = write(folder / "run.toml", """
        solver = "frameps"
        capture = "../sphere.h5"
        out = "results/fp"
        name = "fp-robust"
        error-max = 10
        set = ["threshold=0.01"]

        [options]
        robust = true
        frames = 6
    """)
    monkeypatch.chdir(tmp_path)  # another folder than the file's
    assert main(["run", "--config", str(config), "--json"]) == 0
    got = result(folder / "results" / "fp")
    assert (got["solver"], got["name"], got["error_max_deg"]) == ("frameps", "fp-robust", 10.0)
    assert got["capture"] == str(tmp_path / "sphere.h5")
    assert got["options"] == {**FRAMEPS_DEFAULTS, "robust": True, "frames": 6, "threshold": 0.01}
    assert json.loads(capsys.readouterr().out) == got


def test_the_command_line_overrides_the_file(classic: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    capture = shutil.copy(classic, tmp_path / "sphere.h5")
    other = shutil.copy(classic, tmp_path / "other.h5")
    config = write(tmp_path / "run.toml", """
        solver = "frameps"
        capture = "sphere.h5"
        out = "from-file"
        store = true
        set = ["threshold=0.01", "frames=4"]

        [options]
        robust = true
        threshold = 0.05
    """)
    before = sha256(other)
    out = tmp_path / "from-flags"
    assert run(str(other), "--config", str(config), "--set", "frames=0", "--no-store", "--name", "plain", "-o", str(out)) == 0
    got = result(out)
    # the table comes after set (threshold 0.05), --set after both (frames 0)
    assert got["options"] == {**FRAMEPS_DEFAULTS, "robust": True, "threshold": 0.05, "frames": 0}
    assert (got["capture"], got["name"], got["stored"]) == (str(other), "plain", None)
    assert sha256(other) == before and not (tmp_path / "from-file").exists()
    # the file's options belong to its solver: another solver on the command line meets them as errors
    capsys.readouterr()
    assert run("--config", str(config), "--solver", "eventps") == 2
    err = capsys.readouterr().err
    assert err.startswith(f"pstoolkit: error: {config}: set: solver 'eventps' has no option 'threshold' (options: ") and err.count("\n") == 1
    assert capture.exists()


def test_the_file_s_assignments_come_first_and_the_table_after_set(tmp_path: Path) -> None:
    config = read_config(write(tmp_path / "a.toml", """
        solver = "dualres"
        set = ["epochs=3", "seed=1"]

        [options]
        epochs = 5
        lr = 0.01

        [options.shadow]
        margin_px = 0.5
    """), "run")
    entry = get_registries().solvers.get("dualres")
    assert config.solver_assignments(entry) == ["epochs=3", "seed=1", "epochs=5", "lr=0.01", "shadow.margin_px=0.5"]
    options = entry.parse_options([*config.solver_assignments(entry), "epochs=7"])
    assert (options["epochs"], options["seed"], options["lr"], options["shadow"]) == (7, 1, 0.01, ("margin_px=0.5",))


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ('solver = "frameps"\ndevise = "cpu"\n',
         "unknown key 'devise' (keys: capture, device, error-max, integrate, integrator-options, integrator-set, name, options, out, "
         "scheduler, set, solver, store, workers)"),
        ('solver = 3\n', "solver: expected a string, got an integer 3"),
        ('solver = "frameps"\nerror-max = "30"\n', "error-max: expected a number, got a string '30'"),
        ('solver = "frameps"\nstore = "yes"\n', "store: expected true or false, got a string 'yes'"),
        ('solver = "framepz"\n', "solver: unknown solver 'framepz' (known: "),
        ('solver = "frameps"\nintegrate = "magic"\n', "integrate: unknown "),
        ('solver = "frameps"\n[options]\nframes = "6"\n', "options.frames: expected an integer, got a string '6'"),
        ('solver = "frameps"\n[options]\nrobust = 1\n', "options.robust: expected true or false, got an integer 1"),
        ('solver = "frameps"\n[options]\nframes = -1\n', "options.frames: -1 is below the minimum 0"),
        ('solver = "frameps"\n[options]\nframe = 6\n',
         "options.frame: solver 'frameps' has no option 'frame' (options: dark_fraction, frames, robust, saturation_level, threshold)"),
        ('solver = "frameps"\noptions = 3\n', "options: expected a table of options, got an integer 3"),
        ('solver = "frameps"\nset = "frames=3"\n', "set: expected an array of \"key=value\" strings, got a string 'frames=3'"),
        ('solver = "frameps"\nset = ["frames=x"]\n', "set: option frames: expected int, got 'x'"),
        ('solver = "frameps" x\n',
         "not a valid TOML file (Expected newline or end of document after a statement (at line 1, column 20))"),
    ],
)
def test_a_bad_file_is_one_line_naming_the_file_and_the_key(
    text: str, message: str, classic: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = write(tmp_path / "run.toml", text)
    capsys.readouterr()
    assert main(["run", str(classic), "--config", str(config), "-o", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"pstoolkit: error: {config}: {message}") and err.count("\n") == 1, err
    assert not (tmp_path / "out").exists()


def test_a_missing_file_and_a_result_json_for_batch(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    missing = tmp_path / "nope.toml"
    assert main(["run", "--config", str(missing)]) == 2
    assert capsys.readouterr().err == f"pstoolkit: error: {missing}: no such file\n"
    done = write(tmp_path / "result.json", "{}")
    assert main(["batch", "--config", str(done)]) == 2
    assert capsys.readouterr().err == (
        f"pstoolkit: error: {done}: a result.json describes one run; repeat it with `pstoolkit run --config {done}`\n"
    )


def test_result_json_repeats_a_frameps_run_bit_for_bit(classic: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    first, again = tmp_path / "first", tmp_path / "again"
    assert run(str(classic), "--solver", "frameps", "--set", "robust=true", "--set", "frames=6", "--name", "fp6",
               "--error-max", "12", "-o", str(first)) == 0
    recorded = result(first)
    assert recorded["capture"] == str(classic) and recorded["capture_sha256"] == sha256(classic)
    assert recorded["pstoolkit_version"] == pstoolkit.__version__
    assert recorded["options"] == {**FRAMEPS_DEFAULTS, "robust": True, "frames": 6}
    assert run("--config", str(first / "result.json"), "-o", str(again)) == 0
    repeated = result(again)
    for key in ("solver", "name", "options", "capture", "capture_sha256", "error_max_deg", "mae_deg", "coverage", "maps"):
        assert repeated[key] == recorded[key], key
    for name in ("normal.npy", "albedo.npy", "error.npy"):  # the same numbers, bit for bit
        np.testing.assert_array_equal(np.load(again / name), np.load(first / name))
    assert (again / "normal.png").read_bytes() == (first / "normal.png").read_bytes()


def test_result_json_refuses_a_capture_that_changed(classic: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    capture = Path(shutil.copy(classic, tmp_path / "sphere.h5"))
    first = tmp_path / "first"
    assert run(str(capture), "--solver", "frameps", "-o", str(first)) == 0
    recorded = sha256(capture)
    normal = np.zeros((32, 32, 3), np.float32)
    psfmt.write_result(capture, psfmt.Result("later", {"normal": normal}, solver="flat"))  # the file changes
    changed = sha256(capture)
    capsys.readouterr()
    assert run("--config", str(first / "result.json"), "-o", str(tmp_path / "again")) == 2
    assert capsys.readouterr().err == (
        f"pstoolkit: error: {first / 'result.json'}: capture_sha256: {capture} is not the file that run read (changed since, "
        f"or replaced): its SHA-256 is {changed[:12]}…, the run recorded {recorded[:12]}…; give the capture on the command "
        "line to run on it anyway\n"
    )
    assert not (tmp_path / "again").exists()
    # named on the command line, the capture is the user's choice: the same solver and options run on it
    assert run(str(capture), "--config", str(first / "result.json"), "-o", str(tmp_path / "again")) == 0
    assert result(tmp_path / "again")["capture_sha256"] == changed


def test_result_json_without_a_checksum_or_from_another_version(
    classic: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    first = tmp_path / "first"
    assert run(str(classic), "--solver", "frameps", "-o", str(first)) == 0
    data = result(first)
    older = write(tmp_path / "older.json", json.dumps({k: v for k, v in data.items() if k != "capture_sha256"}))
    capsys.readouterr()
    assert run("--config", str(older), "-o", str(tmp_path / "again")) == 2
    assert capsys.readouterr().err == (
        f"pstoolkit: error: {older}: capture_sha256: not recorded (written by pstoolkit {pstoolkit.__version__}), so {classic} "
        "cannot be checked; give the capture on the command line to run on it anyway\n"
    )
    other = write(tmp_path / "other.json", json.dumps({**data, "pstoolkit_version": "0.0.9"}))
    assert run("--config", str(other), "-o", str(tmp_path / "again")) == 0
    assert capsys.readouterr().err == f"note: {other} was written by pstoolkit 0.0.9, this is {pstoolkit.__version__}: results may differ\n"


def test_result_json_records_the_absolute_capture_and_its_checksum_after_store(
    classic: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    shutil.copy(classic, tmp_path / "c.h5")
    monkeypatch.chdir(tmp_path)
    assert run("c.h5", "--solver", "frameps", "--store", "-o", "out") == 0
    recorded = result(tmp_path / "out")
    assert recorded["capture"] == str(tmp_path / "c.h5")
    # --store wrote the result into the capture: the checksum is of the file as the run left it
    assert recorded["capture_sha256"] == sha256(tmp_path / "c.h5")
    monkeypatch.chdir(tmp_path / "out")
    assert run("--config", "result.json", "-o", str(tmp_path / "again")) == 0


def test_run_replaces_the_result_folder_as_a_unit(hybrid: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 24 B.3: dualres's further maps do not survive a frameps run into the same folder, and no
    temporary folder is left beside it; a folder that holds no result is not deleted."""
    out = tmp_path / "out"
    assert run(str(hybrid), "--solver", "dualres", "--set", "epochs=0", "-o", str(out)) == 0
    assert {"f0.npy", "roughness.png", "cast_shadow.npy", "base_color.png"} <= {p.name for p in out.iterdir()}
    assert run(str(hybrid), "--solver", "frameps", "-o", str(out)) == 0
    assert sorted(p.name for p in out.iterdir()) == FRAMEPS_FILES
    assert result(out)["solver"] == "frameps"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]

    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep")
    capsys.readouterr()
    assert run(str(hybrid), "--solver", "frameps", "-o", str(mine)) == 2
    assert capsys.readouterr().err == (
        f"pstoolkit: error: {mine}: is a folder of other files (no result.json), which writing a result would delete; "
        "choose another output folder (-o DIR) or empty this one\n"
    )
    assert (mine / "notes.txt").read_text() == "keep"
    (tmp_path / "file").write_text("")
    assert run(str(hybrid), "--solver", "frameps", "-o", str(tmp_path / "file")) == 2
    assert capsys.readouterr().err == f"pstoolkit: error: {tmp_path / 'file'}: exists and is not a folder; choose another output folder (-o DIR)\n"
    (mine / "notes.txt").unlink()
    assert run(str(hybrid), "--solver", "frameps", "-o", str(mine)) == 0  # an empty folder is fine


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ('captures = "c"\nsolver = "frameps"\nworker = 2\n',
         "unknown key 'worker' (keys: captures, device, error-max, options, out, scheduler, set, solver, workers)"),
        ('captures = "c"\nsolver = "frameps"\nworkers = "2"\n', "workers: expected an integer, got a string '2'"),
        ('captures = []\nsolver = "frameps"\n', "captures: expected at least one value, got an empty array"),
        ('captures = "c"\nsolver = ["frameps", "nope"]\n', "solver: unknown solver 'nope' (known: "),
        ('captures = "c"\nsolver = "frameps"\n[options]\nreweight = 0\n', "options.reweight: none of the solvers frameps has an option 'reweight'"),
        ('captures = "c"\nsolver = "frameps"\n[options.frameps]\nrobust = "yes"\n',
         "options.frameps.robust: expected true or false, got a string 'yes'"),
        ('captures = "c"\nsolver = "frameps"\nset = ["robust=maybe"]\n', "set: option robust: expected true or false, got 'maybe'"),
    ],
)
def test_batch_file_errors_are_one_line_before_anything_runs(
    text: str, message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = write(tmp_path / "batch.toml", 'out = "results"\n' + text)
    (tmp_path / "c").mkdir()
    capsys.readouterr()
    assert main(["batch", "--config", str(config)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"pstoolkit: error: {config}: {message}") and err.count("\n") == 1, err
    assert not (tmp_path / "results").exists()


def test_batch_takes_its_settings_from_a_toml_file(classic: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Plain [options] keys go to every listed solver that has them, [options.NAME] to solver NAME,
    a table of a registered solver the batch does not run is skipped, --solver overrides the list."""
    folder = tmp_path / "project"
    (folder / "captures").mkdir(parents=True)
    shutil.copy(classic, folder / "captures" / "ball.h5")
    config = write(folder / "batch.toml", """
        captures = "captures"
        solver = ["frameps", "eventps"]
        out = "results"
        workers = 1
        device = "cpu"

        [options]
        threshold = 0.01

        [options.frameps]
        robust = true

        [options.dualres]
        epochs = 2
    """)
    assert main(["batch", "--config", str(config), "--solver", "frameps", "--quiet"]) == 0
    assert sorted(p.name for p in (folder / "results").iterdir()) == ["ball-frameps", "batch.json"]
    got = result(folder / "results" / "ball-frameps")
    assert got["options"] == {**FRAMEPS_DEFAULTS, "robust": True, "threshold": 0.01}
    assert got["capture_sha256"] == sha256(classic)
    # a rerun with the same file finds the pair complete (its options recorded as resolved)
    capsys.readouterr()
    assert main(["batch", "--config", str(config), "--solver", "frameps", "--quiet"]) == 0
    assert "1 pairs: 0 done, 1 skipped, 0 failed" in capsys.readouterr().out
