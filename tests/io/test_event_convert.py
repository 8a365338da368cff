"""``convert raw``/``convert dsec``, ``export --events`` and the EVT 3.0 size in ``info``, end to end."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest

import psfmt
from psfmt.eventfiles import dat, evt3
from psfmt.eventfiles.dsec import write_dsec
from psfmt.eventfiles.rawheader import format_header
from pstoolkit.cli import main


def raw_file(path: Path, words: list[int], width: int = 16, height: int = 12) -> Path:
    path.write_bytes(format_header("EVT3", width, height) + np.asarray(words, "<u2").tobytes())
    return path


def trig(value: int, channel: int = 0) -> int:
    return 0xA000 | (channel << 8) | value


# two exposures on channel 0 ([100, 300) and [1000, 1500) µs), one edge on channel 2, six events
WORDS = [
    0x8000, 0x6000 | 100, trig(1), 0x0003, 0x2800 | 5,
    0x6000 | 200, 0x2000 | 6, trig(1, channel=2),
    0x6000 | 300, trig(0), 0x0004, 0x2800 | 7,
    0x6000 | 1000, trig(1), 0x2800 | 8, 0x2800 | 9,
    0x6000 | 1500, trig(0), 0x2000 | 10,
]


RING = {"elevation_deg": 45.0, "period_us": 1500, "phase_deg": 0.0, "sense": 1, "intensity": [1.0, 1.0, 1.0]}


def test_raw_with_frames_lights_and_calibration(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src = raw_file(tmp_path / "rec.raw", WORDS)
    folder = tmp_path / "frames"
    folder.mkdir()
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (2, 8, 10, 3), dtype=np.uint8)
    for k in range(2):
        cv2.imwrite(str(folder / f"frame_{k:03d}.png"), rgb[k][..., ::-1])
    (tmp_path / "lights.json").write_text(json.dumps({"model": "ring", "params": RING}))
    affine = [[0.5, 0.0, -0.25], [0.0, 0.5, -0.25]]
    (tmp_path / "calib.json").write_text(json.dumps({"event_to_frame": affine, "contrast_pos": 0.2}))
    out = tmp_path / "capture.h5"
    args = ["convert", "raw", str(src), "-o", str(out), "--frames", str(folder)]
    assert main([*args, "--lights", str(tmp_path / "lights.json"), "--calibration", str(tmp_path / "calib.json")]) == 0
    assert capsys.readouterr().out == f"wrote {out}\n"
    with psfmt.read(out) as capture:
        events = capture.events.read()
        assert (capture.events.width, capture.events.height) == (16, 12)
        assert events.x.tolist() == [5, 6, 7, 8, 9, 10] and events.y.tolist() == [3, 3, 4, 4, 4, 4]
        assert events.t.tolist() == [100, 200, 300, 1000, 1000, 1500] and events.p.tolist() == [1, -1, 1, 1, 1, -1]
        assert capture.triggers.t.tolist() == [100, 200, 300, 1000, 1500]
        assert capture.triggers.channel.tolist() == [0, 2, 0, 0, 0]
        frames = capture.frames
        assert np.array_equal(np.asarray(frames.data), rgb)
        assert frames.t_start_us.tolist() == [100, 1000] and frames.t_end_us.tolist() == [300, 1500]
        assert capture.lights.model == "ring" and capture.lights.params["period_us"] == 1500
        assert np.array_equal(capture.calibration.event_to_frame, affine) and capture.calibration.contrast_pos == 0.2
    assert psfmt.validate(out).valid
    (tmp_path / "lights.json").write_text(json.dumps({"model": "ring", "params": {"period_us": 1500}}))
    assert main([*args[:4], str(tmp_path / "bad.h5"), "--lights", str(tmp_path / "lights.json")]) == 2
    assert capsys.readouterr().err == f"pstoolkit: error: {tmp_path / 'bad.h5'}: not written: /lights: parameter 'elevation_deg' is missing\n"
    assert sorted(p.name for p in tmp_path.iterdir() if p.suffix == ".h5") == ["capture.h5"]

    cv2.imwrite(str(folder / "frame_002.png"), rgb[0])
    assert main([*args[:4], str(tmp_path / "three.h5"), *args[5:]]) == 2
    err = capsys.readouterr().err
    assert err == f"pstoolkit: error: {folder}: trigger channel 0 gives 2 exposure window(s) for 3 frame(s)\n"
    assert not (tmp_path / "three.h5").exists()


def test_frames_from_a_capture_keep_their_sensor_attributes(tmp_path: Path) -> None:
    """A capture's frames attached to a recording keep what the sensor said of them, not what their
    data type would imply (12 significant bits in uint16, a clipping level below full scale, a black
    level), so the solvers' saturation masks stay right."""
    rng = np.random.default_rng(2)
    data = rng.integers(0, 4096, (2, 8, 10, 3), dtype=np.uint16)
    frames = psfmt.Frames(data, [100, 1000], [300, 1500], bit_depth=12, saturation=4000.0, black_level=64.0)
    psfmt.write(psfmt.Capture(frames=frames), tmp_path / "frames.h5")
    out = tmp_path / "capture.h5"
    src = raw_file(tmp_path / "rec.raw", WORDS)
    assert main(["convert", "raw", str(src), "-o", str(out), "--frames", str(tmp_path / "frames.h5"), "-q"]) == 0
    with psfmt.read(out) as capture:
        got = capture.frames
        assert np.array_equal(np.asarray(got.data), data) and got.t_start_us.tolist() == [100, 1000]
        assert (got.bit_depth, got.saturation, got.black_level, got.response) == (12, 4000.0, 64.0, "linear")
    assert psfmt.validate(out).valid


def test_backward_steps_and_skipped_words_are_counted(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    src = raw_file(tmp_path / "back.raw", [0x8000, 0x6000 | 50, 0x0001, 0x2000 | 1, 0x6000 | 40, 0x2000 | 2, 0xE000, 0x1000, 0x2000 | 99])
    out = tmp_path / "back.h5"
    with caplog.at_level(logging.WARNING, logger="pstoolkit.eventfiles"):
        assert main(["convert", "raw", str(src), "-o", str(out)]) == 0
    assert caplog.messages == [
        (
            f"{src}: 2 events, 0 triggers from 9 words; 1 OTHERS/CONTINUED words skipped; 1 words of unknown type "
            "skipped; 1 events outside the sensor geometry dropped; 1 events stamped before their predecessor got its time"
        )
    ]
    with psfmt.read(out) as capture:
        assert capture.events.read().t.tolist() == [50, 50]


def event_capture(n: int = 3000, seed: int = 1) -> psfmt.Capture:
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, 40 << 20, n))  # spans two 2^24 µs wraps
    events = psfmt.EventArray(rng.integers(0, 40, n), rng.integers(0, 30, n), t, rng.choice([-1, 1], n))
    return psfmt.Capture(events=psfmt.Events(40, 30, events), description="export test")


@pytest.mark.parametrize("fmt,converter", [("evt3", "raw"), ("evt2", "raw"), ("dat", "dat"), ("dsec", "dsec")])
def test_export_and_convert_back_is_exact(tmp_path: Path, capsys: pytest.CaptureFixture[str], fmt: str, converter: str) -> None:
    capture = event_capture()
    src = tmp_path / "capture.h5"
    psfmt.write(capture, src)
    exported = tmp_path / f"events.{fmt}"
    assert main(["export", str(src), "--events", fmt, "-o", str(exported)]) == 0
    assert capsys.readouterr().out == f"wrote {exported} (3,000 events, {exported.stat().st_size:,} bytes)\n"
    back = tmp_path / "back.h5"
    assert main(["convert", converter, str(exported), "-o", str(back), "-q"]) == 0
    with psfmt.read(back) as again:
        events, original = again.events.read(), capture.events.read()
        assert all(np.array_equal(getattr(events, c), getattr(original, c)) for c in "xytp")
        assert (again.events.width, again.events.height) == (40, 30)
    if fmt == "evt3":
        assert exported.read_bytes() == format_header("EVT3", 40, 30) + evt3.encode(original)
    if fmt == "dat":
        assert exported.read_bytes() == dat.format_header(40, 30) + dat.encode(original)


def test_export_errors_are_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    frames_only = psfmt.Capture(frames=psfmt.Frames(np.zeros((1, 4, 4, 3), np.uint8), light_direction=[[0, 0, 1]]))
    psfmt.write(frames_only, tmp_path / "frames.h5")
    assert main(["export", str(tmp_path / "frames.h5"), "--events", "evt3", "-o", str(tmp_path / "x.raw")]) == 2
    assert capsys.readouterr().err == f"pstoolkit: error: {tmp_path / 'frames.h5'}: holds no events to export\n"
    assert main(["export", str(tmp_path / "frames.h5"), "--events", "aedat", "-o", str(tmp_path / "x")]) == 2
    assert capsys.readouterr().err == "pstoolkit: error: --events 'aedat' is not one of evt3, evt2, dat, dsec\n"
    late = psfmt.EventArray(np.array([1]), np.array([2]), np.array([1 << 33]), np.array([1]))
    psfmt.write(psfmt.Capture(events=psfmt.Events(4, 4, late)), tmp_path / "late.h5")
    assert main(["export", str(tmp_path / "late.h5"), "--events", "dat", "-o", str(tmp_path / "late.dat")]) == 2
    assert capsys.readouterr().err == (
        f"pstoolkit: error: {tmp_path / 'late.h5'}: cannot export as dat: DAT times are uint32 µs: every time must lie in "
        "[0, 4294967295]\n"
    )
    assert not (tmp_path / "late.dat").exists()
    garbage = tmp_path / "garbage.raw"
    garbage.write_bytes(b"\x00\x01" * 50)
    assert main(["convert", "raw", str(garbage), "-o", str(tmp_path / "g.h5")]) == 2
    assert capsys.readouterr().err == f"pstoolkit: error: {garbage}: no '% evt' or '% format' header line: not a Prophesee RAW file\n"


def test_dsec_convert_with_declared_geometry(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    events = event_capture(500).events.read()
    src = tmp_path / "d.h5"
    write_dsec(src, [events], len(events), 40, 30)
    out = tmp_path / "d_capture.h5"
    with caplog.at_level(logging.WARNING, logger="pstoolkit.eventfiles"):
        assert main(["convert", "dsec", str(src), "-o", str(out), "--width", "20", "--height", "30", "-q"]) == 0
    inside = int((events.x < 20).sum())
    assert caplog.messages == [f"{src}: {len(events) - inside:,} events outside 20×30 dropped"]
    with psfmt.read(out) as capture:
        assert len(capture.events) == inside and capture.events.width == 20


def test_info_reports_the_real_evt3_size(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    capture = event_capture()
    path = tmp_path / "c.h5"
    psfmt.write(capture, path)
    assert main(["info", "--json", str(path)]) == 0
    encoding = json.loads(capsys.readouterr().out)["event_encoding"]
    size = len(evt3.encode(capture.events.read()))
    assert encoding["evt3_bytes"] == size and encoding["estimate_bytes"] == 6000
    rate = psfmt.data_rate(capture, event_bytes=size)
    assert encoding["data_rate_events"] == pytest.approx(rate.event_rate, rel=1e-12)
    assert main(["info", str(path)]) == 0
    assert f"  EVT 3.0: {size:,} bytes ({size / 3000:.2f} per event; 16-bit estimate 6,000)" in capsys.readouterr().out


def test_dsec_coordinates_beyond_uint16_are_dropped_and_counted(tmp_path: Path, caplog: pytest.LogCaptureFixture, capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 19, item 6: an x of 65541 or 4·10⁹ stored as uint32 is not wrapped into the sensor."""
    src = tmp_path / "wide.h5"
    with h5py.File(src, "w") as f:
        f.attrs["width"], f.attrs["height"] = 640, 480
        f["events/x"] = np.array([3, 65541, 7, 4_000_000_000], np.uint32)
        f["events/y"] = np.array([1, 2, 3, 4], np.uint32)
        f["events/p"] = np.array([1, 0, 1, 1], np.uint8)
        f["events/t"] = np.array([10, 20, 30, 40], np.uint32)
        f["t_offset"] = np.int64(0)
    out = tmp_path / "wide_capture.h5"
    with caplog.at_level(logging.WARNING, logger="pstoolkit.eventfiles"):
        assert main(["convert", "dsec", str(src), "-o", str(out), "-q"]) == 0
    assert caplog.messages == [f"{src}: 2 events outside 640×480 dropped"]
    with psfmt.read(out) as capture:
        events = capture.events.read()
        assert events.x.tolist() == [3, 7] and events.t.tolist() == [10, 30]
    with h5py.File(src, "r+") as f:
        del f.attrs["width"]
        del f.attrs["height"]
    capsys.readouterr()
    assert main(["convert", "dsec", str(src), "-o", str(tmp_path / "no_width.h5")]) == 2
    assert capsys.readouterr().err == (
        f"pstoolkit: error: {src}: coordinates reach x = 4000000000, y = 4, beyond the 65536 pixels a side of an event sensor; "
        "give --width and --height to keep the events inside them\n"
    )
    assert main(["convert", "dsec", str(src), "-o", str(tmp_path / "given.h5"), "--width", "640", "--height", "480", "-q"]) == 0


def test_a_recording_without_events_needs_allow_empty(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 19, item 15: a RAW file with only a header, or with every event outside its geometry,
    is refused (no file) unless --allow-empty asks for the empty capture."""
    header_only = raw_file(tmp_path / "header.raw", [])
    outside = raw_file(tmp_path / "outside.raw", [0x8000, 0x6000 | 100, 0x0050, 0x2800 | 40], width=16, height=12)
    expected = {
        header_only: "no events to convert",
        outside: "no events to convert (0 events, 0 triggers from 4 words; 1 events outside the sensor geometry dropped)",
    }
    for src, why in expected.items():
        out = tmp_path / f"{src.stem}.h5"
        capsys.readouterr()
        assert main(["convert", "raw", str(src), "-o", str(out)]) == 2
        assert capsys.readouterr().err == f"pstoolkit: error: {src}: {why}; --allow-empty writes the empty capture anyway\n"
        assert not out.exists()
        assert main(["convert", "raw", str(src), "-o", str(out), "--allow-empty", "-q"]) == 0
        with psfmt.read(out) as capture:
            assert len(capture.events) == 0
