"""Issue 33, items 9–13 and 15: settings files and result records that crash or overflow, "solved
pixel", huge seeds and progress callbacks, unbounded workers and tiles, an infinite error scale.
Every one gives one line and exit code 2 (``pstoolkit.io.textdata``, ``solved_pixels``,
``check_error_max``, ``cluster.max_parallel``)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from helpers.captures import sample_capture

import psfmt
import pstoolkit
from pstoolkit.cli import main
from pstoolkit.errors import UserError
from pstoolkit.io.normalmap import write_normal_npy
from pstoolkit.io.textdata import MAX_TEXT_BYTES, read_json, read_toml
from pstoolkit.solve.cluster import max_parallel
from pstoolkit.solve.tiles import plan_tiles
from pstoolkit.view.sample import write_sphere_result


def one_line(capsys: pytest.CaptureFixture[str], *argv: str) -> str:
    """Run the command, expect exit code 2 and one error line; return it."""
    capsys.readouterr()
    code = main(list(argv))
    err = capsys.readouterr().err
    assert code == 2, err
    assert len(err.strip().splitlines()) == 1 and err.startswith("pstoolkit: error: "), err
    return err


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("records") / "c.h5"
    psfmt.write(sample_capture("frames"), path)
    return path


@pytest.fixture
def result_folder(tmp_path: Path) -> Path:
    folder = tmp_path / "sphere-frameps"
    write_sphere_result(folder, 16, depth=False)
    return folder


DEEP_JSON = "[" * 100_000 + "]" * 100_000
HOSTILE_RESULTS = {
    "nested 200k deep": b'{"object": "o", "name": "n", "x": ' + b"[" * 200_000 + b"]" * 200_000 + b"}",
    "invalid UTF-8": b'{"object": "o\xff\xfe", "name": "n"}',
    "a 5000-digit integer": b'{"object": "o", "name": "n", "seconds": 1' + b"0" * 5000 + b"}",
    "mae_deg of 4000 digits": b'{"object": "o", "name": "n", "mae_deg": 1' + b"0" * 4000 + b"}",
    "mae_deg of 400 digits": b'{"object": "o", "name": "n", "mae_deg": 1' + b"0" * 400 + b"}",
}


# --- 9. settings: TOML and result.json ------------------------------------------------------------

@pytest.mark.parametrize("command", ["run", "batch"])
def test_toml_nested_1000_deep_is_one_line(tmp_path: Path, capture: Path, capsys: pytest.CaptureFixture[str], command: str) -> None:
    settings = tmp_path / "s.toml"
    settings.write_text("x = " + "[" * 1000)
    args = [command, str(capture), "--solver", "frameps", "--config", str(settings)] + (["-o", str(tmp_path / "o")] if command == "batch" else [])
    err = one_line(capsys, *args)
    assert f"{settings}: not a valid TOML file" in err


def test_result_json_settings_nested_or_overflowing(tmp_path: Path, capture: Path, capsys: pytest.CaptureFixture[str]) -> None:
    deep = tmp_path / "deep" / "result.json"
    deep.parent.mkdir()
    deep.write_text('{"solver": "frameps", "capture": "c.h5", "x": ' + DEEP_JSON + "}")
    assert f"{deep}: not valid JSON (nested more than 64 levels deep)" in one_line(capsys, "run", "--config", str(deep))
    big = tmp_path / "big" / "result.json"
    big.parent.mkdir()
    big.write_text(json.dumps({"solver": "frameps", "capture": str(capture)})[:-1] + ', "error_max_deg": 1' + "0" * 400 + "}")
    assert f"{big}: not valid JSON (an integer of 401 digits" in one_line(capsys, "run", "--config", str(big), "-o", str(tmp_path / "o"))


def test_toml_integers_beyond_64_bits_and_depth(tmp_path: Path) -> None:
    settings = tmp_path / "s.toml"
    settings.write_text("workers = 1" + "0" * 30 + "\n")
    with pytest.raises(UserError, match="integer outside the 64-bit range"):
        read_toml(settings)
    settings.write_text("x = " + "[" * 70 + "]" * 70 + "\n")
    with pytest.raises(UserError, match="nested more than 64 levels deep"):
        read_toml(settings)
    settings.write_text("x = " + "[" * 60 + "1" + "]" * 60 + "\n")  # within the limit: read
    value, depth = read_toml(settings)["x"], 1
    while isinstance(value, list):
        value, depth = value[0], depth + 1
    assert (depth, value) == (61, 1)


# --- 10. eval and report on hostile result.json; one size limit ---------------------------------------

@pytest.mark.parametrize("name", list(HOSTILE_RESULTS))
def test_eval_and_report_on_a_hostile_result_json(result_folder: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], name: str) -> None:
    path = result_folder / "result.json"
    path.write_bytes(HOSTILE_RESULTS[name])
    assert str(path) in one_line(capsys, "eval", str(result_folder))
    assert str(path) in one_line(capsys, "report", str(result_folder), "-o", str(tmp_path / "r.md"))
    assert str(path) in one_line(capsys, "view", str(result_folder), "--no-browser", "--port", "0")
    assert not (tmp_path / "r.md").exists()


def test_a_sparse_5_gb_result_json_is_refused_by_its_size(result_folder: Path, capture: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = result_folder / "result.json"
    with open(path, "wb") as fh:
        fh.truncate(5 << 30)  # sparse: no disk used
    expected = f"{path}: {5 << 30} bytes, over the {MAX_TEXT_BYTES} bytes a JSON or TOML file may have"
    for argv in (["eval", str(result_folder)], ["integrate", str(result_folder)], ["run", "--config", str(path)]):
        assert expected in one_line(capsys, *argv)


def test_a_fifo_is_refused_not_waited_on(tmp_path: Path) -> None:
    fifo = tmp_path / "result.json"
    os.mkfifo(fifo)
    with pytest.raises(UserError, match="not a regular file"):
        read_json(fifo)


# --- 11. one rule for "solved pixel" ------------------------------------------------------------------

def test_integrate_leaves_out_tiny_normals(result_folder: Path, capsys: pytest.CaptureFixture[str]) -> None:
    normal = np.load(result_folder / "normal.npy")
    inside = np.flatnonzero(np.any(normal != 0, axis=-1))
    tiny = np.unravel_index(inside[:5], normal.shape[:2])
    normal[tiny] = [0.0, 0.0, 1e-30]
    write_normal_npy(result_folder / "normal.npy", normal)
    capsys.readouterr()
    assert main(["integrate", str(result_folder), "--json", "-q"]) == 0, capsys.readouterr().err
    depth = np.load(result_folder / "depth.npy")
    assert np.isnan(depth[tiny]).all()
    assert np.isfinite(depth).sum() == inside.size - 5
    for integrator in ("poisson", "bini"):  # both integrators: all tiny is no pixel, in one line
        write_normal_npy(result_folder / "normal.npy", np.where(normal != 0, np.float32(1e-30), np.float32(0)))
        assert "no pixel to integrate" in one_line(capsys, "integrate", str(result_folder), "--integrator", integrator)


# --- 12. huge seeds, a progress that is not a function ------------------------------------------------

def test_seed_beyond_64_bits_is_one_line(capture: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    err = one_line(capsys, "run", str(capture), "--solver", "dualres", "--set", "seed=18446744073709551616", "-o", str(tmp_path / "o"))
    assert "option seed: 18446744073709551616 is outside the 64-bit integers" in err
    with pytest.raises(UserError, match="option seed: 1180591620717411303424 is outside the 64-bit integers"):
        pstoolkit.solve_capture(capture, "dualres", seed=2**70)


def test_progress_must_be_callable(capture: Path) -> None:
    with pytest.raises(UserError, match="progress must be a function progress.fraction, message. or None, not int"):
        pstoolkit.solve_capture(capture, "frameps", progress=5)  # type: ignore[arg-type]


# --- 13. workers, threads, tiles ----------------------------------------------------------------------

def test_workers_in_a_batch_toml_are_capped(tmp_path: Path, capture: Path, capsys: pytest.CaptureFixture[str]) -> None:
    settings = tmp_path / "batch.toml"
    settings.write_text(f'captures = ["{capture}"]\nsolver = "frameps"\nworkers = 100000\n')
    err = one_line(capsys, "batch", "--config", str(settings), "-o", str(tmp_path / "out"))
    assert f"--workers 100000: more than this machine can run ({max_parallel()}" in err
    assert not (tmp_path / "out").exists()


def test_threads_and_tiles_are_capped(capture: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    err = one_line(capsys, "run", str(capture), "--solver", "eventps", "--set", "window_us=1000", "--set", "threads=100000",
                   "-o", str(tmp_path / "o"))
    assert f"option threads: 100000 is above the maximum {max_parallel()}" in err
    with pytest.raises(UserError, match="cuts the 4096×4096 frame into 16777216 tiles, over 4096"):
        plan_tiles(4096, 4096, tile_px=1, overlap_px=0)
    assert len(plan_tiles(4096, 4096, tile_px=64, overlap_px=0)) == 4096


# --- 15. the error scale: finite and sane -------------------------------------------------------------

@pytest.mark.parametrize("value", ["inf", "1e308", "nan", "0", "181"])
def test_error_max_must_be_a_sane_angle(capture: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], value: str) -> None:
    for command in ("run", "batch"):
        err = one_line(capsys, command, str(capture), "--solver", "frameps", "--error-max", value, "-o", str(tmp_path / command))
        assert "expected a number of degrees above 0 and at most 180" in err
    assert not any(tmp_path.iterdir())
