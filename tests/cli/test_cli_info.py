"""``pstoolkit info``: counts, duration, event rate and the data rate of known captures."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from helpers.captures import CREATED, PERIOD_US, sample_capture

import psfmt
from pstoolkit.cli import main

N_EVENTS = 4000
EVENT_STEP_US = 7
# 24 RGB 8-bit frames at the 64×64 target resolution: 100 % of the data rate
REFERENCE_BYTES = 24 * 64 * 64 * 3


def known_capture(kind: str = "hybrid", period_us: int = PERIOD_US) -> psfmt.Capture:
    """The hybrid sample with events every 7 µs from t = 0 and a ring light of the given period."""
    capture = sample_capture(kind, seed=0)
    if capture.events is not None:
        t = np.arange(N_EVENTS, dtype=np.int64) * EVENT_STEP_US
        events = psfmt.EventArray(t % 32, (t // 32) % 32, t, np.where(t % 3 == 0, -1, 1))
        capture.events = psfmt.Events(32, 32, events)
    if capture.lights is not None:
        capture.lights.params["period_us"] = period_us
    return capture


def info_json(path: Path, capsys: pytest.CaptureFixture[str]) -> dict:
    capsys.readouterr()
    assert main(["info", "--json", str(path)]) == 0
    out, err = capsys.readouterr()
    assert err == ""
    return json.loads(out)


def test_info_json_numbers_of_a_hybrid_capture(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "hybrid.h5"
    psfmt.write(known_capture(), path)
    d = info_json(path, capsys)
    assert (d["file"], d["kind"], d["format_version"], d["creator"], d["created"]) == (
        str(path), "hybrid", "1.3", "tests 9.9", CREATED)
    assert d["camera"] == {"model": "orthographic"}
    assert d["frames"] == {"count": 3, "width": 64, "height": 64, "channels": 3, "dtype": "uint8", "bit_depth": 8,
                           "saturation": 255.0, "black_level": 0.0, "exposure_ms": [10.0, 10.0, 10.0]}
    last = (N_EVENTS - 1) * EVENT_STEP_US
    duration_s = (last + 1) / 1e6
    assert d["events"] == {"count": N_EVENTS, "width": 32, "height": 32, "t_first_us": 0, "t_last_us": last,
                           "duration_s": pytest.approx(duration_s, rel=1e-12),
                           "rate_ev_per_s": pytest.approx(N_EVENTS / duration_s, rel=1e-12)}
    assert d["event_sensor"] == {"contrast_pos": 0.15, "contrast_neg": 0.2, "refractory_us": 500.0,
                                 "refractory_rule": "rate-limited", "refractory_rule_recorded": True,
                                 "event_to_frame": [[2.0, 0.0, 0.5], [0.0, 2.0, 0.5]], "event_to_frame_recorded": True}
    assert d["lights"] == {"model": "ring", "params": {"elevation_deg": 43.0, "period_us": PERIOD_US,
                                                       "phase_deg": 90.0, "sense": -1, "t0_us": 0}}
    assert d["ground_truth"] == ["normal", "mask", "albedo", "depth", "f0", "roughness"]
    assert d["results"] == {"eventps": {"solver": "eventps", "seconds": 1.25}}
    rate = d["data_rate"]
    assert rate["periods"] == 1.0
    assert rate["frames"] == pytest.approx(3 * 64 * 64 * 3 / REFERENCE_BYTES, rel=1e-12) == 0.125
    assert rate["events"] == pytest.approx(2 * N_EVENTS / REFERENCE_BYTES, rel=1e-12)
    assert rate["total"] == pytest.approx((3 * 64 * 64 * 3 + 2 * N_EVENTS) / REFERENCE_BYTES, rel=1e-12)


def test_info_text_of_a_hybrid_capture(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "hybrid.h5"
    psfmt.write(known_capture(), path)
    capsys.readouterr()
    assert main(["info", str(path)]) == 0
    out, err = capsys.readouterr()
    total = 100 * (3 * 64 * 64 * 3 + 2 * N_EVENTS) / REFERENCE_BYTES
    assert err == ""
    assert out.splitlines() == [
        f"{path}: hybrid capture, format 1.3, by tests 9.9 at {CREATED}",
        "  description: hybrid sample, seed 0",
        "  frames: 3 × 64×64×3 uint8 (8-bit, saturation 255), exposure 10, 10, 10 ms",
        "  camera: orthographic",
        "  events: 4,000 at 32×32, 27.994 ms, 0.143 M events/s",
        "  event sensor: contrast +0.15/−0.2, refractory 500 µs, rate-limited",
        "  event→frame affine: [2 0 0.5; 0 2 0.5] (event pixel centres to frame pixels)",
        "  lights: ring (elevation_deg=43.0, period_us=30000, phase_deg=90.0, sense=-1, t0_us=0)",
        "  ground truth: normal, mask, albedo, depth, f0, roughness",
        "  results: eventps (eventps, 1.25 s)",
        f"  data rate: {total:.1f} % of 24 RGB frames per period (frames 12.5 %, events 2.7 %, 1 period(s))",
        "  EVT 3.0: 17,762 bytes (4.44 per event; 16-bit estimate 8,000), data rate 18.5 % (events 6.0 %)",
    ]
    assert f"{total:.1f}" == "15.2"


def test_data_rate_is_per_light_period(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "two.h5"
    psfmt.write(known_capture(period_us=PERIOD_US // 2), path)
    rate = info_json(path, capsys)["data_rate"]
    assert rate["periods"] == 2.0
    assert rate["total"] == pytest.approx((3 * 64 * 64 * 3 + 2 * N_EVENTS) / 2 / REFERENCE_BYTES, rel=1e-12)


def test_info_of_events_only_and_frames_only_captures(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    psfmt.write(known_capture("events"), tmp_path / "events.h5")
    d = info_json(tmp_path / "events.h5", capsys)
    assert d["kind"] == "events" and "frames" not in d and d["events"]["count"] == N_EVENTS
    # without frames the target resolution is the ground truth's 64×64
    assert d["data_rate"]["total"] == pytest.approx(2 * N_EVENTS / REFERENCE_BYTES, rel=1e-12)
    assert d["data_rate"]["frames"] == 0.0

    psfmt.write(known_capture("frames"), tmp_path / "frames.h5")
    d = info_json(tmp_path / "frames.h5", capsys)
    assert d["kind"] == "frames" and "events" not in d and "lights" not in d
    assert d["frames"]["count"] == 6 and d["frames"]["instantaneous_lights"] is True
    assert d["data_rate"]["total"] == 0.25 and d["data_rate"]["events"] == 0.0
    assert main(["info", str(tmp_path / "frames.h5")]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[2] == "  frames: 6 × 64×64×3 uint8 (8-bit, saturation 255), instantaneous lights"
    assert lines[3:5] == ["  camera: orthographic", "  lights: none"]


def test_info_lists_a_result_written_later(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "hybrid.h5"
    psfmt.write(known_capture(), path)
    normal = np.zeros((64, 64, 3), np.float32)
    normal[..., 2] = 1
    psfmt.write_result(path, psfmt.Result("dualres", {"normal": normal}, solver="dualres", seconds=61.5))
    assert info_json(path, capsys)["results"] == {
        "dualres": {"solver": "dualres", "seconds": 61.5},
        "eventps": {"solver": "eventps", "seconds": 1.25},
    }


def test_a_capture_that_records_no_refractory_rule_has_the_default(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    capture = known_capture()
    capture.calibration.refractory_rule = None
    capture.calibration.contrast_neg = None
    path = tmp_path / "older.h5"
    psfmt.write(capture, path)
    sensor = info_json(path, capsys)["event_sensor"]
    assert (sensor["refractory_rule"], sensor["refractory_rule_recorded"], sensor["contrast_neg"]) == ("reset-at-end", False, None)
    assert main(["info", str(path)]) == 0
    assert "  event sensor: contrast +0.15/−unknown, refractory 500 µs, reset-at-end (not recorded: the format's default)" in (
        capsys.readouterr().out.splitlines())


def test_strings_from_the_file_reach_the_terminal_without_control_characters(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 19, item 9: escape sequences (window title, clear screen), carriage returns, a line break
    and a direction override in the description, the creator and a result name are not printed."""
    capture = known_capture()
    capture.description = "ball\x1b]0;owned\x07 under\x1b[2J light\rX\nlights: fake\u202eevil"
    capture.creator = "psfmt\x1b[8m"
    path = tmp_path / "c.h5"
    psfmt.write(capture, path)
    psfmt.write_result(path, psfmt.Result("r\x1b[31m", {"normal": np.zeros((64, 64, 3), np.float32)}, solver="s\x9b1m"))
    for command in (["info", str(path)], ["validate", str(path)]):
        capsys.readouterr()
        main(command)
        out, err = capsys.readouterr()
        assert not any(c in out + err for c in "\x1b\x07\r\x9b\u202e"), command
    main(["info", str(path)])
    lines = capsys.readouterr().out.splitlines()
    assert "  description: ball]0;owned under[2J light X lights: fakeevil" in lines
    assert not any(line.startswith("lights: fake") for line in lines)
    assert lines[0].endswith(f"by psfmt[8m {capture.creator_version}".rstrip() + f" at {capture.created}")
    assert "  results: eventps (eventps, 1.25 s), r[31m (s1m, 0.00 s)" in lines
    info = info_json(path, capsys)  # JSON escapes them: the values stay as stored
    assert info["description"] == capture.description


def test_info_shows_a_perspective_camera(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    capture = known_capture()
    capture.calibration.camera_model = "perspective"
    capture.calibration.intrinsics = np.array([[500.0, 0.0, 31.5], [0.0, 510.0, 30.25], [0.0, 0.0, 1.0]])
    path = tmp_path / "pinhole.h5"
    psfmt.write(capture, path)
    assert info_json(path, capsys)["camera"] == {"model": "perspective", "fx": 500.0, "fy": 510.0, "cx": 31.5, "cy": 30.25,
                                                 "skew": 0.0}
    assert main(["info", str(path)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[3] == "  camera: perspective, fx 500, fy 510, cx 31.5, cy 30.25 px"

    capture.calibration.intrinsics[0, 1] = 0.5
    psfmt.write(capture, path)
    assert info_json(path, capsys)["camera"]["skew"] == 0.5
    assert main(["info", str(path)]) == 0
    assert capsys.readouterr().out.splitlines()[3] == "  camera: perspective, fx 500, fy 510, cx 31.5, cy 30.25 px, skew 0.5"


def test_info_shows_the_event_to_frame_affine_recorded_or_assumed(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 24 B.5: the calibration's event→frame affine in JSON and text; without one, the affine the
    solvers assume (the same field of view: 32 event pixels over 64 frame pixels), said to be assumed."""
    capture = known_capture()
    capture.calibration.event_to_frame = np.array([[1.98, 0.01, 0.75], [-0.02, 2.01, 0.25]])
    path = tmp_path / "calibrated.h5"
    psfmt.write(capture, path)
    sensor = info_json(path, capsys)["event_sensor"]
    assert sensor["event_to_frame"] == [[1.98, 0.01, 0.75], [-0.02, 2.01, 0.25]] and sensor["event_to_frame_recorded"] is True
    assert main(["info", str(path)]) == 0
    assert "  event→frame affine: [1.98 0.01 0.75; -0.02 2.01 0.25] (event pixel centres to frame pixels)" in (
        capsys.readouterr().out.splitlines())

    capture.calibration.event_to_frame = None
    psfmt.write(capture, path)
    sensor = info_json(path, capsys)["event_sensor"]
    assert sensor["event_to_frame"] == [[2.0, 0.0, 0.5], [0.0, 2.0, 0.5]] and sensor["event_to_frame_recorded"] is False
    assert main(["info", str(path)]) == 0
    assert ("  event→frame affine: [2 0 0.5; 0 2 0.5] (event pixel centres to frame pixels) (not recorded: the same field "
            "of view assumed)") in capsys.readouterr().out.splitlines()
