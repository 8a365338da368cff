"""``convert aedat4``: AEDAT4 files written by iniVation's dv-processing come back as hybrid captures
(events, frames with their exposure windows, trigger edges, the identity event→frame affine) that
validate and that dualres's preprocessing takes; damaged and crafted files are refused in one line.

The files are written with dv-processing (``dv.io.MonoCameraWriter``), the library DV itself uses;
the converter reads them with the ``aedat`` package (see ``plugins/pstoolkit_eventfiles/aedat4.py``).
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import pytest

import psfmt
from pstoolkit.cli import main

pytest.importorskip("aedat", reason="the aedat package (extra 'aedat4') is not installed")
dv = pytest.importorskip("dv_processing", reason="dv-processing (extra 'aedat4') is not installed")

WIDTH, HEIGHT = 64, 48
PERIOD_US = 30_000
T0_US = 1_000_000
# three exposures tiling one light period, as a ring-light capture records them
WINDOWS = [(T0_US + k * PERIOD_US // 3, T0_US + (k + 1) * PERIOD_US // 3) for k in range(3)]
RING = {"elevation_deg": 45.0, "period_us": PERIOD_US, "phase_deg": 0.0, "sense": 1, "t0_us": T0_US, "intensity": [1.0, 1.0, 1.0]}


def sample(seed: int = 0, n: int = 3000) -> dict[str, np.ndarray]:
    """Sorted events over the period, three RGB frames, the trigger edges of each exposure (channel 0)
    and of the camera's generator (channel 1), a timestamp reset and the APS exposure markers."""
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(T0_US, T0_US + PERIOD_US, n))
    triggers = []
    for start, end in WINDOWS:
        triggers += [(start, 1), (start, 8), (end, 2), (end, 9)]
    triggers += [(T0_US + 500, 4), (T0_US + 900, 5), (T0_US + 29_000, 0)]
    triggers.sort()
    return {
        "t": t,
        "x": rng.integers(0, WIDTH, n),
        "y": rng.integers(0, HEIGHT, n),
        "on": rng.random(n) < 0.5,
        "frames": rng.integers(0, 256, (3, HEIGHT, WIDTH, 3), dtype=np.uint8),
        "triggers": np.array(triggers, np.int64),
    }


def _dv_frame(start: int, end: int, image: np.ndarray) -> object:
    """A dv-processing frame exposed over [start, end) µs; dv-processing keeps OpenCV's BGR order."""
    pixels = np.ascontiguousarray(image[..., ::-1] if image.ndim == 3 else image)
    return dv.Frame(int(start), int(end - start), 0, 0, pixels, dv.FrameSource.SENSOR)


def write_aedat4(path: Path, data: dict[str, np.ndarray], *, frame_size: tuple[int, int] = (WIDTH, HEIGHT),
                 compression: str = "LZ4", packets: int = 3) -> Path:
    """``data`` as a DAVIS recording: event packets and frames interleaved in time, then the triggers."""
    config = dv.io.MonoCameraWriter.Config("DAVIS346_test", getattr(dv.CompressionType, compression))
    config.addEventStream((WIDTH, HEIGHT))
    config.addFrameStream(frame_size)
    config.addTriggerStream()
    writer = dv.io.MonoCameraWriter(str(path), config)
    frames = list(zip(WINDOWS, data["frames"]))
    for part in np.array_split(np.arange(len(data["t"])), packets):
        while frames and frames[0][0][0] <= data["t"][part[0]]:
            (start, end), rgb = frames.pop(0)
            writer.writeFrame(_dv_frame(start, end, rgb))
        store = dv.EventStore()
        for i in part:
            store.push_back(int(data["t"][i]), int(data["x"][i]), int(data["y"][i]), bool(data["on"][i]))
        writer.writeEvents(store)
    for (start, end), rgb in frames:
        writer.writeFrame(_dv_frame(start, end, rgb))
    for t, kind in data["triggers"]:
        writer.writeTrigger(dv.Trigger(int(t), dv.TriggerType(int(kind))))
    del writer  # closing writes the file's table
    return path


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_aedat4(tmp_path_factory.mktemp("aedat4") / "rec.aedat4", sample())


def test_round_trip_events_frames_windows_triggers(
    recording: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture
) -> None:
    data = sample()
    lights = tmp_path / "lights.json"
    lights.write_text(json.dumps({"model": "ring", "params": RING}))
    out = tmp_path / "capture.h5"
    assert main(["convert", "aedat4", str(recording), "-o", str(out), "--lights", str(lights)]) == 0
    assert capsys.readouterr().out == f"wrote {out}\n"
    # the timestamp reset is the one trigger that is neither an edge nor an APS marker
    assert [r.getMessage() for r in caplog.records] == [f"{recording}: 1 trigger(s) that are no edge (timestamp resets, pulses) skipped"]
    with psfmt.read(out) as capture:
        events = capture.events.read()
        assert (capture.events.width, capture.events.height) == (WIDTH, HEIGHT)
        assert np.array_equal(events.t, data["t"]) and np.array_equal(events.x, data["x"]) and np.array_equal(events.y, data["y"])
        assert np.array_equal(events.p, np.where(data["on"], 1, -1))
        frames = capture.frames
        assert frames.color_order == "RGB" and frames.bit_depth == 8
        assert np.array_equal(np.asarray(frames.data), data["frames"])
        assert frames.t_start_us.tolist() == [w[0] for w in WINDOWS] and frames.t_end_us.tolist() == [w[1] for w in WINDOWS]
        # in file order: the external input's rising (1) and falling (2) edges on channel 0, the generator's (4, 5) on 1
        kinds = sorted([(s, 1) for s, _ in WINDOWS] + [(e, 2) for _, e in WINDOWS] + [(T0_US + 500, 4), (T0_US + 900, 5)])
        edge = {1: (0, 1), 2: (0, 0), 4: (1, 1), 5: (1, 0)}
        edges = [(t, *edge[kind]) for t, kind in kinds]
        got = list(zip(capture.triggers.t.tolist(), capture.triggers.channel.tolist(), capture.triggers.value.tolist()))
        assert got == edges
        assert np.array_equal(capture.calibration.event_to_frame, [[1, 0, 0], [0, 1, 0]])
        assert capture.lights.model == "ring" and capture.lights.params["period_us"] == PERIOD_US
        assert "compression LZ4" in capture.description
    assert psfmt.validate(out).valid


def test_dualres_preprocessing_takes_the_converted_capture(recording: Path, tmp_path: Path) -> None:
    from pstoolkit_dualres.preprocess import PreprocessOptions, preprocess

    (tmp_path / "lights.json").write_text(json.dumps({"model": "ring", "params": RING}))
    (tmp_path / "calib.json").write_text(json.dumps({"contrast_pos": 0.2, "contrast_neg": 0.2, "refractory_us": 100}))
    out = tmp_path / "capture.h5"
    args = ["convert", "aedat4", str(recording), "-o", str(out), "-q"]
    assert main([*args, "--lights", str(tmp_path / "lights.json"), "--calibration", str(tmp_path / "calib.json")]) == 0
    with psfmt.read(out) as capture:
        assert capture.calibration.contrast_pos == 0.2
        assert np.array_equal(capture.calibration.event_to_frame, [[1, 0, 0], [0, 1, 0]])
        pre = preprocess(capture, PreprocessOptions())
    assert (pre.height, pre.width, pre.event_height, pre.event_width) == (HEIGHT, WIDTH, HEIGHT, WIDTH)
    assert np.array_equal(pre.event_to_frame, [[1, 0, 0], [0, 1, 0]])


def test_zstd_and_uncompressed_files_read_alike(tmp_path: Path) -> None:
    data = sample(seed=1, n=500)
    captures = []
    for compression in ("ZSTD", "NONE"):
        src = write_aedat4(tmp_path / f"{compression}.aedat4", data, compression=compression, packets=2)
        out = tmp_path / f"{compression}.h5"
        assert main(["convert", "aedat4", str(src), "-o", str(out), "-q"]) == 0
        with psfmt.read(out) as capture:
            captures.append((capture.events.read().t, np.asarray(capture.frames.data)))
    assert np.array_equal(captures[0][0], data["t"]) and np.array_equal(captures[1][0], data["t"])
    assert np.array_equal(captures[0][1], data["frames"]) and np.array_equal(captures[1][1], data["frames"])


def test_grey_frames_keep_their_bit_depth(tmp_path: Path) -> None:
    data = sample(seed=3, n=200)
    for dtype, maximum in ((np.uint8, 255), (np.uint16, 1023)):
        grey = np.random.default_rng(4).integers(0, maximum + 1, (3, HEIGHT, WIDTH)).astype(dtype)
        src = write_aedat4(tmp_path / f"{dtype.__name__}.aedat4", data | {"frames": grey}, packets=1)
        out = tmp_path / f"{dtype.__name__}.h5"
        assert main(["convert", "aedat4", str(src), "-o", str(out), "-q"]) == 0
        with psfmt.read(out) as capture:
            frames = capture.frames
            assert frames.color_order == "L" and frames.data.dtype == dtype
            assert np.array_equal(np.asarray(frames.data)[..., 0], grey)


def _first_packet(blob: bytes) -> int:
    (length,) = struct.unpack_from("<I", blob, 14)
    return 18 + length


def _packets(blob: bytes) -> list[tuple[int, int, int]]:
    """(stream id, first byte, end) of each packet of a file that has no table at its end."""
    at, out = _first_packet(blob), []
    while at < len(blob):
        stream, size = struct.unpack_from("<iI", blob, at)
        out.append((stream, at + 8, at + 8 + size))
        at += 8 + size
    return out


def _refused(src: Path, out: Path, capsys: pytest.CaptureFixture[str]) -> str:
    assert main(["convert", "aedat4", str(src), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"pstoolkit: error: {src}: ")
    assert [p.name for p in out.parent.iterdir() if out.name in p.name] == []  # no capture, no temporary file
    return err[len(f"pstoolkit: error: {src}: ") : -1]


def test_damaged_and_crafted_files_are_refused_in_one_line(recording: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    blob = recording.read_bytes()
    first = _first_packet(blob)
    out = tmp_path / "out.h5"
    cases = {
        "cut.aedat4": blob[: len(blob) // 2],
        "magic.aedat4": b"#!AER-DAT3.1\r\n" + blob[14:],
        "header.aedat4": blob[:14] + struct.pack("<I", 0xFFFF_FFF0) + blob[18:],
        "packet.aedat4": blob[: first + 4] + struct.pack("<I", 0xFFFF_FFFF) + blob[first + 8 :],
        # aedat 2.3 aborts the process on a description that is not UTF-8: caught before it sees the file
        "utf8.aedat4": blob.replace(b"<dv version", b"<\xffv version", 1),
        "lz4.aedat4": blob[: first + 40] + bytes(b ^ 0xFF for b in blob[first + 40 : first + 60]) + blob[first + 60 :],
    }
    expected = {
        "cut.aedat4": "truncated: the header places the file's table at byte",
        "magic.aedat4": "no '#!AER-DAT4.0' line at the start: not an AEDAT4 file",
        "header.aedat4": "the AEDAT4 header claims 4,294,967,280 bytes (at most 16,777,216 are read)",
        "packet.aedat4": f"packet 0 at byte {first:,} claims 4,294,967,295 bytes (at most 67,108,864)",
        "utf8.aedat4": "the AEDAT4 header's description is not UTF-8 text (byte ",
        "lz4.aedat4": "not a readable AEDAT4 file: ",
    }
    for name, content in cases.items():
        src = tmp_path / name
        src.write_bytes(content)
        assert _refused(src, out, capsys).startswith(expected[name]), name


def test_frames_going_back_or_off_the_geometry_and_time_jumps_are_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    data = sample(seed=2, n=300)
    out = tmp_path / "out.h5"
    small = write_aedat4(tmp_path / "small.aedat4", data | {"frames": data["frames"][:, :24, :32]}, frame_size=(32, 24))
    assert _refused(small, out, capsys) == (
        "the frame stream is 32×24, the event stream 64×48: convert aedat4 reads cameras whose frames and events share pixels (DAVIS)"
    )
    roi = write_aedat4(tmp_path / "roi.aedat4", data | {"frames": data["frames"][:, :24, :32]})
    assert _refused(roi, out, capsys) == "frame 0 is 32×24 at (0, 0), not the sensor's 64×48: a DAVIS's frames and events share pixels"
    # dv-processing refuses to write a frame earlier than the last, so the third frame's times are
    # rewritten in an uncompressed file: its timestamp and exposure start become the first frame's - 1
    plain = write_aedat4(tmp_path / "plain.aedat4", data, compression="NONE", packets=1)
    blob = bytearray(plain.read_bytes())
    frame_packets = [(at, end) for stream, at, end in _packets(bytes(blob)) if stream == 1]
    at, end = frame_packets[2]
    third = struct.pack("<q", WINDOWS[2][0])
    assert blob[at:end].count(third) == 2
    blob[at:end] = blob[at:end].replace(third, struct.pack("<q", WINDOWS[0][0] - 1))
    back = tmp_path / "back.aedat4"
    back.write_bytes(bytes(blob))
    assert _refused(back, out, capsys) == (
        f"frame 2's exposure starts at {WINDOWS[0][0] - 1} µs, before frame 1's at {WINDOWS[1][0]} µs"
    )
    # one damaged event time 2^50 µs on: the capture's millisecond index would take 9 TB
    blob = bytearray(plain.read_bytes())
    at, end = next((at, end) for stream, at, end in _packets(bytes(blob)) if stream == 0)
    last = struct.pack("<q", int(data["t"][-1]))
    assert blob[at:end].count(last) >= 1
    blob[at:end] = blob[at:end].replace(last, struct.pack("<q", 1 << 50))
    jump = tmp_path / "jump.aedat4"
    jump.write_bytes(bytes(blob))
    assert _refused(jump, out, capsys).startswith(
        f"events from {data['t'][0]} µs to {1 << 50} µs: the capture's millisecond index would take 9,007,199,246,"
    )
