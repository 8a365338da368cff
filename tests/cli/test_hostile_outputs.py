"""Issue 33, items 1–3: an output path never replaces something that is not a regular file, never
replaces an input, and SIGTERM leaves no temporary file (``psfmt.atomic.check_target``, the one
output-path rule of every command that writes)."""

from __future__ import annotations

import os
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest
from helpers.captures import sample_capture

import psfmt
from pstoolkit.cli import main


@pytest.fixture
def hybrid(tmp_path: Path) -> Path:
    path = tmp_path / "hybrid.h5"
    psfmt.write(sample_capture("hybrid", n_events=500), path)
    return path


def run_cli(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str]:
    capsys.readouterr()
    code = main(list(argv))
    return code, capsys.readouterr().err


def _fifo(path: Path) -> Path:
    os.mkfifo(path)
    return path


def _link(path: Path) -> Path:
    (path.parent / "elsewhere.bin").write_bytes(b"keep me")
    path.symlink_to(path.parent / "elsewhere.bin")
    return path


@pytest.mark.parametrize("make", [_fifo, _link], ids=["fifo", "symlink"])
@pytest.mark.parametrize("fmt", ["dat", "evt3"])
def test_export_refuses_an_output_that_is_not_a_regular_file(
    hybrid: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], make: object, fmt: str
) -> None:
    out = make(tmp_path / f"out.{fmt}")  # type: ignore[operator]
    before = os.lstat(out)
    code, err = run_cli(capsys, "export", str(hybrid), "--events", fmt, "-o", str(out))
    assert code == 2
    assert len(err.strip().splitlines()) == 1 and str(out) in err
    assert "symbolic link" in err or "not a regular file" in err
    after = os.lstat(out)
    assert (after.st_mode, after.st_ino) == (before.st_mode, before.st_ino)
    assert (tmp_path / "elsewhere.bin").read_bytes() == b"keep me" if make is _link else True


def test_simulate_refuses_a_fifo_before_rendering(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = _fifo(tmp_path / "out.h5")
    code, err = run_cli(capsys, "simulate", "sphere", "--size", "16", "--periods", "1", "-o", str(out))
    assert code == 2 and "not a regular file" in err
    assert os.path.exists(out) and not out.is_file()


def test_character_device_is_refused(tmp_path: Path, hybrid: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # a device node of its own (never the system's /dev/null, which a failing run would replace)
    device = tmp_path / "null"
    try:
        os.mknod(device, stat.S_IFCHR | 0o666, os.makedev(1, 3))
    except PermissionError:
        pytest.skip("making a device node needs root")
    for argv in (["eval", str(hybrid), "-o", str(device)], ["export", str(hybrid), "--events", "evt3", "-o", str(device)]):
        code, err = run_cli(capsys, *argv)
        assert code == 2 and f"{device}: exists and is not a regular file" in err
        assert stat.S_ISCHR(os.lstat(device).st_mode)


@pytest.mark.parametrize("fmt", ["dat", "evt3"])
def test_export_refuses_to_replace_its_input(hybrid: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], fmt: str) -> None:
    hard = tmp_path / "hard.h5"
    os.link(hybrid, hard)
    for out in (hybrid, hard):
        code, err = run_cli(capsys, "export", str(hybrid), "--events", fmt, "-o", str(out))
        assert code == 2 and f"is the input {hybrid}" in err
    with psfmt.read(hybrid) as capture:  # still the capture it was
        assert capture.events is not None and len(capture.events) == 500


def test_convert_dat_refuses_to_replace_its_input(hybrid: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    dat = tmp_path / "x.dat"
    assert run_cli(capsys, "export", str(hybrid), "--events", "dat", "-o", str(dat))[0] == 0
    original = dat.read_bytes()
    code, err = run_cli(capsys, "convert", "dat", str(dat), "-o", str(dat))
    assert code == 2 and f"{dat}: is the input" in err
    assert dat.read_bytes() == original


def test_run_refuses_a_result_folder_that_holds_the_capture(hybrid: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    folder = tmp_path / "results"
    folder.mkdir()
    (folder / "result.json").write_text("{}")
    inside = folder / "c.h5"
    hybrid.rename(inside)
    code, err = run_cli(capsys, "run", str(inside), "--solver", "frameps", "-o", str(folder))
    assert code == 2 and "holds it" in err
    assert inside.is_file()
    link = tmp_path / "link"
    link.symlink_to(folder)
    code, err = run_cli(capsys, "run", str(inside), "--solver", "frameps", "-o", str(link))
    assert code == 2 and "symbolic link" in err


def test_sigterm_during_simulate_leaves_no_temporary_file(tmp_path: Path) -> None:
    out = tmp_path / "big.h5"
    process = subprocess.Popen(
        [sys.executable, "-c", "from pstoolkit.cli import main; main()", "simulate", "sphere", "--size", "64", "--periods", "400", "-q", "-o", str(out)],
        stderr=subprocess.PIPE, text=True,
    )
    deadline = time.monotonic() + 120
    while not list(tmp_path.glob(".big.h5.*.tmp")) and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    assert process.poll() is None, "the simulation ended before it could be terminated"
    process.send_signal(signal.SIGTERM)
    _, err = process.communicate(timeout=120)
    assert process.returncode == 143, err
    assert err.strip() == "pstoolkit: error: terminated"
    assert list(tmp_path.iterdir()) == []
