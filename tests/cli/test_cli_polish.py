"""Issue 24, part A: the command line as people expect it — ``--version``, one rich progress bar
(whole message, time remaining; silent off a terminal and under ``-q``, which every command takes),
``--json`` wherever a command reports something, help pages without typer's placeholders, one
``--device`` default, and ``--help`` / ``info`` without torch, numba or matplotlib."""

from __future__ import annotations

import io
import json
import re
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import typer
from helpers.captures import sample_capture
from helpers.replay import PERIOD_US, write_recording
from rich.console import Console

import psfmt
import pstoolkit
from pstoolkit.cli import _commands, main
from pstoolkit.cli import app as cli_app
from pstoolkit.cli.app import progress_bar

REPORTING = [
    "batch", "calibrate affine", "calibrate lights", "capture",
    "convert", "eval", "export", "info", "integrate", "plugins", "report", "run", "simulate", "validate",
]
"""Every command that reports something (``view`` serves a page until Ctrl-C: it reports nothing)."""


def fake_terminal(clock: list[float] | None = None) -> tuple[Console, io.StringIO]:
    """A rich console that is a terminal (wide, no colour) writing into a string; its clock is
    ``clock[0]`` when given, so that the time remaining comes out the same on any machine."""
    screen = io.StringIO()
    get_time = None if clock is None else (lambda: clock[0])
    return Console(file=screen, force_terminal=True, width=120, color_system=None, get_time=get_time), screen


def command_names() -> list[str]:
    """Every leaf command, a group's as "group sub" (``calibrate affine``)."""
    _commands()
    names = []
    for name, command in typer.main.get_command(cli_app.app).commands.items():  # type: ignore[attr-defined]
        subcommands = getattr(command, "commands", None)
        names += [f"{name} {sub}" for sub in subcommands] if subcommands else [name]
    return sorted(names)


def run_cli(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    capsys.readouterr()
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def json_of(capsys: pytest.CaptureFixture[str], *argv: str, code: int = 0) -> Any:
    """The one JSON value a command prints on stdout (``json.loads`` fails on anything else there)."""
    got, out, err = run_cli(capsys, *argv)
    assert got == code, err
    return json.loads(out)


@pytest.fixture
def hybrid(tmp_path: Path) -> Path:
    path = tmp_path / "hybrid.h5"
    psfmt.write(sample_capture("hybrid"), path)
    return path


@pytest.fixture
def classic(tmp_path: Path) -> Path:
    path = tmp_path / "classic.h5"
    psfmt.write(sample_capture("frames"), path)
    return path


# --- 1. --version -----------------------------------------------------------------------------------


def test_version_prints_the_package_version(capsys: pytest.CaptureFixture[str]) -> None:
    assert run_cli(capsys, "--version") == (0, f"pstoolkit {pstoolkit.__version__}\n", "")


# --- 2. the progress bar and -q -------------------------------------------------------------------------


def test_the_bar_shows_the_whole_message_and_the_time_remaining() -> None:
    clock = [0.0]
    console, screen = fake_terminal(clock)
    report = progress_bar("dualres", console=console)
    for epoch in range(1, 151):
        clock[0] += 0.1
        report(epoch / 150, f"epoch {epoch}/150 loss 0.0123")
    drawn = screen.getvalue()
    # halfway after 7.5 s: 7.5 s to go, beside the whole message (the old bar cut it at 20 characters)
    assert re.search(r"dualres .* 50% 0:00:0[78] epoch 75/150 loss 0\.0123", drawn), drawn[-500:]
    final = drawn.split("\r")[-1]
    assert "100%" in final and "epoch 150/150 loss 0.0123" in final


def test_no_bar_off_a_terminal_or_when_quiet() -> None:
    console, screen = fake_terminal()
    assert progress_bar("x", quiet=True, console=console) is pstoolkit.no_progress
    plain = Console(file=io.StringIO(), force_terminal=False)
    assert progress_bar("x", console=plain) is pstoolkit.no_progress
    assert screen.getvalue() == ""


def test_every_command_takes_quiet_and_json_where_it_reports(capsys: pytest.CaptureFixture[str]) -> None:
    names = command_names()
    assert set(REPORTING) | {"view"} == set(names)
    for name in names:
        code, out, _ = run_cli(capsys, *name.split(), "--help")
        assert code == 0
        assert "-q, --quiet" in out, name
        assert ("--json" in out) == (name in REPORTING), name


@pytest.fixture
def terminal(monkeypatch: pytest.MonkeyPatch) -> io.StringIO:
    """stderr made a terminal: every bar the commands open draws into the returned string."""
    console, screen = fake_terminal()
    monkeypatch.setattr(cli_app, "_stderr_console", lambda: console)
    return screen


@pytest.mark.parametrize("command", ["validate", "run", "export"])
def test_quiet_writes_nothing_to_stderr_where_a_terminal_shows_a_bar(
    command: str, hybrid: Path, classic: Path, tmp_path: Path, terminal: io.StringIO, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = {
        "validate": ["validate", str(hybrid)],
        "run": ["run", str(hybrid), "--solver", "frameps", "--device", "cpu", "--store"],
        "export": ["export", str(classic), "--frames", "diligent"],
    }[command]
    outs = iter(tmp_path / f"out{i}" for i in range(2))
    out_args: Callable[[], list[str]] = lambda: [] if command == "validate" else ["-o", str(next(outs))]  # noqa: E731
    code, _, err = run_cli(capsys, *argv, *out_args())
    assert code == 0, err
    assert "100%" in terminal.getvalue()  # the bar is there without -q
    terminal.truncate(0)
    terminal.seek(0)
    code, _, err = run_cli(capsys, *argv, *out_args(), "-q")
    assert code == 0, err
    assert (terminal.getvalue(), err) == ("", "")


# --- 3. --json --------------------------------------------------------------------------------------------


def test_simulate_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "sphere.h5"
    d = json_of(capsys, "simulate", "sphere", "-o", str(out), "--size", "16", "--json")
    with psfmt.read(out) as capture:
        assert capture.events is not None
        assert d["file"] == str(out)
        assert d["frames"] == {"count": capture.frames.count, "width": 16, "height": 16}
        assert d["events"] == {"count": len(capture.events), "width": 8, "height": 8}
    assert d["seconds"] > 0


def test_export_json_for_events_and_frames(hybrid: Path, classic: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    raw = tmp_path / "events.raw"
    d = json_of(capsys, "export", str(hybrid), "--events", "evt3", "-o", str(raw), "--json")
    assert d == {"file": str(raw), "format": "evt3", "events": 5000, "bytes": raw.stat().st_size}
    folder = tmp_path / "object"
    d = json_of(capsys, "export", str(classic), "--frames", "diligent", "-o", str(folder), "--json")
    assert d["folder"] == str(folder) and d["format"] == "diligent" and d["normal_gt"] is True
    assert d["images"] == len((folder / "filenames.txt").read_text().split()) and d["width"] == d["height"] == 64


def test_convert_json(hybrid: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    raw = tmp_path / "events.raw"
    assert main(["export", str(hybrid), "--events", "evt3", "-o", str(raw), "-q"]) == 0
    out = tmp_path / "converted.h5"
    d = json_of(capsys, "convert", "raw", str(raw), "-o", str(out), "--json")
    assert d == {"converter": "raw", "written": [str(out)]}
    assert out.is_file()


def test_calibrate_json(hybrid: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    event = np.array([[1.0, 2.0], [10.0, 3.0], [4.0, 12.0], [14.0, 15.0]])
    frame = 2.0 * event + 0.5
    pairs = tmp_path / "pairs.txt"
    np.savetxt(pairs, np.hstack([event, frame]))
    d = json_of(capsys, "calibrate", "affine", str(hybrid), "--pairs", str(pairs), "--no-store", "--json")
    np.testing.assert_allclose(d["affine"], [[2.0, 0.0, 0.5], [0.0, 2.0, 0.5]], atol=1e-9)
    assert d["rms_px"] < 1e-9 and d["max_px"] < 1e-9
    assert (d["pairs"], d["from"], d["stored_in"]) == (4, "pairs file", [])


def test_batch_json(hybrid: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "batch"
    assert main(["run", str(hybrid), "--solver", "frameps", "--device", "cpu", "-o", str(out / "hybrid-frameps"), "-q"]) == 0
    # the pair is complete, so no cluster starts and the unreachable scheduler is never asked
    d = json_of(capsys, "batch", str(hybrid), "--solver", "frameps", "-o", str(out), "--device", "cpu", "--scheduler", "tcp://127.0.0.1:9", "--json")
    assert d == {"pairs": 1, "done": 0, "skipped": 1, "failed": 0, "out": str(out), "log": str(out / "batch.json"), "failures": []}


def test_capture_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    recording = write_recording(tmp_path / "rec.h5")
    out = tmp_path / "out.h5"
    d = json_of(
        capsys, "capture", "--light", "ringlight", "--port", f"ringlightsim://{tmp_path.name}", "--source", f"replay:{recording}",
        "--source-set", "speed=0", "-o", str(out), "--json",
    )
    with psfmt.read(out) as capture:
        assert capture.frames is not None and capture.events is not None
        assert d == {"file": str(out), "frames": capture.frames.count, "events": len(capture.events), "periods": 1, "period_us": PERIOD_US}


def test_report_json(hybrid: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    result = tmp_path / "results" / "hybrid-frameps"
    assert main(["run", str(hybrid), "--solver", "frameps", "--device", "cpu", "-o", str(result), "-q"]) == 0
    d = json_of(capsys, "report", str(result.parent), "-o", str(tmp_path / "report.md"), "--json")
    assert d["markdown"] == str(tmp_path / "report.md") and d["html"] == str(tmp_path / "report.html")
    assert d["figures"] and all(Path(f).is_file() for f in d["figures"])


# --- 4. help pages ------------------------------------------------------------------------------------------

PLACEHOLDER = re.compile(r"\{[A-Za-z_][\w-]*\}|<(?:list\[)?(?:str|int|float|bool|path|text|integer|file|datetime)\]?(?:\.\.\.)?>")
"""typer's ``{scene}`` (a required argument in the usage line) and type labels (``<list[str]>``, ``<path>``)."""


def help_pages(capsys: pytest.CaptureFixture[str]) -> dict[str, str]:
    pages = {"pstoolkit": run_cli(capsys, "--help")[1]}
    for name in command_names():
        code, out, err = run_cli(capsys, *name.split(), "--help")
        assert code == 0, err
        pages[name] = out
    pages["convert raw"] = run_cli(capsys, "convert", "raw", "--help")[1]
    return pages


def test_no_help_page_shows_a_placeholder_or_an_unrounded_default(capsys: pytest.CaptureFixture[str]) -> None:
    for name, page in help_pages(capsys).items():
        assert not PLACEHOLDER.search(page), f"{name}: {PLACEHOLDER.search(page)}"
        assert not re.search(r"default: -?\d+\.\d{7,}", page), name
        usage = page.splitlines()[0]
        assert usage.startswith("Usage: pstoolkit") and not re.search(r"[{}<>]", usage), usage


def test_help_names_values_plainly(capsys: pytest.CaptureFixture[str]) -> None:
    pages = help_pages(capsys)
    assert pages["simulate"].startswith("Usage: pstoolkit simulate [OPTIONS] SCENE\n")
    # optional: the captures may come from --config
    assert pages["batch"].startswith("Usage: pstoolkit batch [OPTIONS] [CAPTURES...]\n")
    assert pages["run"].startswith("Usage: pstoolkit run [OPTIONS] [CAPTURE]\n")
    assert pages["export"].startswith("Usage: pstoolkit export [OPTIONS] CAPTURE\n")
    simulate = " ".join(pages["simulate"].split())
    for shown in ("--size INTEGER", "--period-ms FLOAT", "[default: 33.3333]", "-o, --out PATH", "--set KEY=VALUE", "--shadows / --no-shadows"):
        assert shown in simulate, shown


def test_every_device_option_defaults_to_auto() -> None:
    _commands()
    group = typer.main.get_command(cli_app.app)
    devices = {
        name: param.default
        for name, command in group.commands.items()  # type: ignore[attr-defined]
        for param in command.params
        if "--device" in getattr(param, "opts", ())
    }
    assert set(devices) == {"batch", "run", "simulate"} and set(devices.values()) == {"auto"}


# --- 5. light imports ---------------------------------------------------------------------------------------


def test_help_and_info_load_neither_torch_nor_numba_nor_matplotlib(hybrid: Path) -> None:
    code = (
        "import sys\n"
        "from pstoolkit.cli import main\n"
        "assert main(['--help']) == 0\n"
        "assert main(['simulate', '--help']) == 0\n"
        f"assert main(['info', {str(hybrid)!r}]) == 0\n"
        f"assert main(['info', '--json', {str(hybrid)!r}]) == 0\n"
        "print('LOADED', sorted({'torch', 'numba', 'matplotlib'} & set(sys.modules)))\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert "EVT 3.0:" in done.stdout  # info sized the events (the codec that used to load numba)
    assert done.stdout.splitlines()[-1] == "LOADED []"
