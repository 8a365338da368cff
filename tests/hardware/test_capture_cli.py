"""``pstoolkit capture`` end to end: the simulated ring light and a replayed recording make a valid
capture that frameps solves to the recording's accuracy; a disconnect, Ctrl-C or a short recording
leave the lights off and no file; bad input is one line and exit code 2."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from helpers.calibration import led_target
from helpers.replay import PERIOD_US, write_recording

import psfmt
from pstoolkit import hookimpl
from pstoolkit.cli import main
from pstoolkit.evaluation.metrics import angular_error_deg
from pstoolkit.plugin import manager as plugins
from pstoolkit.plugin.manager import get_registries
from pstoolkit.plugin.registry import Registry
from pstoolkit.solve.base import run_solver
from pstoolkit_replay.source import Replay
from pstoolkit_ringlight.protocol_ringlightsim import device


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_recording(tmp_path_factory.mktemp("rec") / "rec.h5")


def capture(recording: Path, out: Path, port: str, *extra: str) -> int:
    return main(["capture", "--light", "ringlight", "--port", port, "--source", f"replay:{recording}", "-o", str(out), "-q", *extra])


def frameps_mae(path: Path, truth: psfmt.GroundTruth) -> float:
    entry = get_registries().solvers.get("frameps")
    result, _ = run_solver(entry, psfmt.load(path), entry.parse_options([]))
    errors = angular_error_deg(result.normal, truth.normal, truth.mask)
    return float(np.where(result.mask, errors, 90.0)[truth.mask].mean())


def test_capture_from_the_simulated_light_and_a_replay_solves_like_the_recording(recording: Path, tmp_path: Path) -> None:
    out = tmp_path / "out.h5"
    port = f"ringlightsim://{tmp_path.name}"
    assert capture(recording, out, port, "--periods", "2", "--source-set", "speed=0", "--description", "bench") == 0
    report = psfmt.validate(out)
    assert report.valid, [f.text for f in report.errors]
    original = psfmt.load(recording)
    got = psfmt.load(out)
    assert np.array_equal(np.asarray(got.frames.data), np.asarray(original.frames.data))
    assert np.array_equal(got.frames.t_start_us, original.frames.t_start_us)
    for c in "xytp":
        assert np.array_equal(getattr(got.events.data, c), getattr(original.events.data, c))
    assert got.lights.model == "sampled" and got.lights.params["times_us"].shape == (60,)
    assert got.lights.params["period_us"] == PERIOD_US
    assert np.array_equal(got.calibration.event_to_frame, original.calibration.event_to_frame)
    assert got.calibration.contrast_pos == 0.15 and got.calibration.refractory_us == 2000.0
    assert got.triggers.t.tolist() == [0, 10, 6000, 6010] and got.triggers.value.tolist() == [1, 0, 1, 0]
    assert (got.creator, got.description) == ("pstoolkit capture", "bench")
    assert not device(tmp_path.name).lit()
    truth = original.ground_truth
    recorded, captured = frameps_mae(recording, truth), frameps_mae(out, truth)
    assert recorded < 5.0 and abs(captured - recorded) < 0.1


def test_one_period_keeps_only_its_frames_and_events(recording: Path, tmp_path: Path) -> None:
    out = tmp_path / "one.h5"
    assert capture(recording, out, "sim", "--source-set", "speed=0") == 0
    with psfmt.read(out) as got, psfmt.read(recording) as original:
        assert got.frames.count == 6 and got.frames.t_end_us[-1] == PERIOD_US
        assert len(got.events) == len(original.events.window(0, PERIOD_US))


def test_a_disconnect_mid_capture_leaves_no_file_and_the_watchdog_turns_the_lights_off(
    recording: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out.h5"
    out.write_bytes(b"an earlier file")
    # ID, OFF, WDG, CFG and GO are answered; the sixth request (a keepalive while recording) finds the device gone
    port = f"ringlightsim://{tmp_path.name}?disconnect=6"
    code = capture(recording, out, port, "--periods", "2", "--set", "watchdog_ms=100", "--set", "timeout_ms=20", "--source-set", "speed=0.1")
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"pstoolkit: error: ring light on {port}: connection lost during PING and the port cannot be reopened "
                   f"(could not open port {port}: [Errno 2] No such file or directory)"]
    assert out.read_bytes() == b"an earlier file" and sorted(p.name for p in tmp_path.iterdir()) == ["out.h5"]
    dev = device(tmp_path.name)
    time.sleep(0.15)
    assert not dev.lit() and dev.fault == "WDOG"


@pytest.mark.parametrize(("reset", "code"), [("0", 0), ("1", 2)])
def test_a_reconnect_mid_capture_keeps_the_capture_only_if_the_sweep_survived(
    recording: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], reset: str, code: int
) -> None:
    out = tmp_path / "out.h5"
    port = f"ringlightsim://{tmp_path.name}?blip=6&reset={reset}"  # the link breaks at the first keepalive
    args = ["--periods", "2", "--set", "watchdog_ms=100", "--set", "timeout_ms=20", "--source-set", "speed=0.1"]
    assert capture(recording, out, port, *args) == code
    if code == 0:
        assert psfmt.validate(out).valid and psfmt.load(out).frames.count == 12
    else:
        assert capsys.readouterr().err.strip() == f"pstoolkit: error: ring light on {port}: the connection was lost and the sweep did not survive it"
        assert not out.exists()
    assert not device(tmp_path.name).lit()


class InterruptedReplay(Replay):
    """A replay whose operator presses Ctrl-C after three packets."""

    name = "interrupted-replay"

    def stream(self, sweep: Any) -> Any:
        for n, packet in enumerate(super().stream(sweep)):
            if n == 3:
                raise KeyboardInterrupt
            yield packet


class InterruptPlugin:
    @hookimpl
    def pstoolkit_register_backends(self, registry: Registry) -> None:
        registry.register(InterruptedReplay)


@pytest.fixture
def interrupting_plugin() -> Iterator[None]:
    plugins.reset()
    plugins.register_plugin(InterruptPlugin(), "test-interrupt")
    yield
    plugins.reset()


def test_ctrl_c_leaves_the_lights_off_and_no_file(recording: Path, tmp_path: Path, interrupting_plugin: None, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out.h5"
    args = ["capture", "--light", "ringlight", "--port", f"ringlightsim://{tmp_path.name}", "--source", f"interrupted-replay:{recording}"]
    assert main([*args, "-o", str(out), "--source-set", "speed=0"]) == 130
    # issue 19, item 14: the line says what the user needs to know after a Ctrl-C
    assert capsys.readouterr().err == f"pstoolkit: error: interrupted: the lights are off and {out} was not written\n"
    assert list(tmp_path.iterdir()) == []
    assert not device(tmp_path.name).lit() and device(tmp_path.name).fault == "NONE"  # turned off, not by the watchdog


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--source", "replay"], "--source 'replay': expected NAME:LOCATION (e.g. replay:recording.h5)"),
        (["--light", "replay"], "backend 'replay' is a source, not a light"),
        (["--light", "laser"], "unknown backend 'laser' (known: replay, ringlight)"),
        (["--periods", "3"], "the sources ended after 2.00 of 3 period(s)"),
        (["--period-ms", "5"], "replay {rec}: recorded with a 6000 µs light period, but the light is set to 5000 µs"),
        (["--source-set", "volume=3"], "--source-set 'volume=3': no source given has option 'volume'"),
        (["--set", "elevation_deg=95"], "option elevation_deg: 95.0 is above the maximum 90"),
        (["--direction", "up"], "--direction 'up': expected ccw or cw"),
        (["--trigger", "always"], "--trigger 'always': expected one of off, period, exposure"),
        (["--calibration", "{rec}.missing"], "--calibration {rec}.missing: does not exist"),
        (["--port", "ringlightsim://{tmp}?firmware=blinky"], "ring light on ringlightsim://{tmp}?firmware=blinky: wrong firmware blinky 1.0.0 "
         "(protocol 1); expected pstoolkit-ringlight with protocol 1 (flash examples/firmware/ringlight)"),
    ],
)
def test_bad_input_is_one_line(recording: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], message: str) -> None:
    base = {"--light": "ringlight", "--port": f"ringlightsim://{tmp_path.name}", "--source": f"replay:{recording}", "-o": str(tmp_path / "out.h5")}
    extra = []
    for key, value in zip(args[::2], args[1::2]):
        if key in base:
            base[key] = value.replace("{tmp}", tmp_path.name)
        else:
            extra += [key, value.replace("{rec}", str(recording))]
    argv = ["capture", *[x for kv in base.items() for x in kv], "--source-set", "speed=0", *extra]
    if "--source-set" in args:
        argv.remove("speed=0")
        argv.remove("--source-set")
    assert main(argv) == 2
    assert capsys.readouterr().err.strip().splitlines() == [f"pstoolkit: error: {message.replace('{rec}', str(recording)).replace('{tmp}', tmp_path.name)}"]
    assert not (tmp_path / "out.h5").exists()


def test_the_affine_from_calibrate_is_stored_with_the_capture(recording: Path, tmp_path: Path) -> None:
    target = led_target(tmp_path / "target.h5")
    assert main(["calibrate", "affine", str(target)]) == 0
    out = tmp_path / "out.h5"
    assert capture(recording, out, f"ringlightsim://{tmp_path.name}", "--calibration", str(target), "--source-set", "speed=0") == 0
    with psfmt.read(out) as got, psfmt.read(target) as calibrated:
        assert np.array_equal(got.calibration.event_to_frame, calibrated.calibration.event_to_frame)
        assert got.calibration.contrast_pos == 0.15  # the rest of the calibration comes from the source
        assert not np.allclose(got.calibration.event_to_frame, psfmt.scale_affine(0.5))  # not the recording's own
