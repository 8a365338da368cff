"""Issue 19: files that declare more than they hold, damaged and hostile files.

Each is made by writing a valid capture and breaking it (with h5py or by changing bytes). Whatever a
file holds, ``validate``, the reader and the CLI answer with a finding or one "damaged file" line,
in bounded time and memory, and they agree.
"""

from __future__ import annotations

import os
import signal
import struct
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import h5py
import numpy as np
import pytest
from helpers.captures import sample_capture
from helpers.mutations import probe

import psfmt
from psfmt import isolate
from psfmt.eventfiles.rawheader import format_header
from pstoolkit.cli import main


def written(tmp_path: Path, kind: str = "hybrid", name: str = "capture.h5") -> Path:
    path = tmp_path / name
    psfmt.write(sample_capture(kind, seed=0, n_events=3000), path)
    return path


def edited(tmp_path: Path, edit: Callable[[h5py.File], None], kind: str = "hybrid") -> Path:
    path = written(tmp_path, kind)
    with h5py.File(path, "r+") as f:
        edit(f)
    return path


def declared(name: str, shape: tuple[int, ...], dtype: object, chunks: tuple[int, ...]) -> Callable[[h5py.File], None]:
    """An edit that replaces (or adds) dataset ``name`` by a compressed one that declares ``shape``
    and stores nothing: a few hundred bytes of metadata for any size."""

    def edit(f: h5py.File) -> None:
        if name in f:
            del f[name]
        f.create_dataset(name, shape=shape, dtype=dtype, chunks=chunks, compression="gzip")

    return edit


@contextmanager
def deadline(seconds: int) -> Iterator[None]:
    """Fail the test instead of waiting for ever (the scans are Python loops, which SIGALRM stops)."""

    def expired(signum: int, frame: object) -> None:
        raise TimeoutError(f"still running after {seconds} s")

    previous = signal.signal(signal.SIGALRM, expired)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


def assert_refused(path: Path, message: str, capsys: pytest.CaptureFixture[str]) -> None:
    """The reader refuses with ``message``, validate reports it as the first error (exit 1) and
    ``info`` says it in one line (exit 2); everything within seconds."""
    with deadline(60):
        report = psfmt.validate(path)
        assert [f.text for f in report.errors][:1] == [message]
        with pytest.raises(psfmt.FormatError) as caught:
            psfmt.read(path)
        assert str(caught.value) == f"{path}: {message}"
        capsys.readouterr()
        assert main(["info", str(path)]) == 2
        assert capsys.readouterr() == ("", f"pstoolkit: error: {path}: {message}\n")
        assert main(["validate", str(path)]) == 1
        assert f"{path}: error: {message}\n" in capsys.readouterr().out


def add_big_result(f: h5py.File) -> None:
    group = f.require_group("results/big")
    group.attrs.update({"solver": "x", "options": "{}"})
    declared("results/big/normal", (200_000, 200_000, 3), np.float32, (64, 64, 3))(f)


DECLARED = {
    "a result map of 480 GB": (
        add_big_result,
        "/results/big/normal: declares (200000, 200000, 3) float32 (480,000,000,000 bytes) but the file stores no data for it",
    ),
    "frames of 90 GB": (
        declared("frames/data", (3, 100_000, 100_000, 3), np.uint8, (1, 16, 100_000, 3)),
        "/frames/data: declares (3, 100000, 100000, 3) uint8 (90,000,000,000 bytes) but the file stores no data for it",
    ),
    "10¹⁰ triggers": (
        lambda f: [declared(f"triggers/{c}", (10**10,), d, (1 << 16,))(f) for c, d in (("t", np.int64), ("channel", np.uint8), ("value", np.int8))],
        "/triggers/channel: declares (10000000000,) uint8 (10,000,000,000 bytes) but the file stores no data for it",
    ),
}


@pytest.mark.parametrize("name", DECLARED)
def test_item_1_sizes_are_checked_against_what_the_file_stores(tmp_path: Path, name: str, capsys: pytest.CaptureFixture[str]) -> None:
    edit, message = DECLARED[name]
    path = edited(tmp_path, edit)
    assert path.stat().st_size < 500_000
    assert_refused(path, message, capsys)


def test_item_1_results_and_triggers_are_read_lazily(tmp_path: Path) -> None:
    path = written(tmp_path)
    stored = psfmt.Result("stored", {"normal": np.ones((64, 64, 3), np.float32)}, solver="x")
    psfmt.write_result(path, stored)
    with psfmt.read(path) as capture:
        assert isinstance(capture.triggers, psfmt.events.H5Triggers) and capture.triggers._table is None
        assert len(capture.triggers) == len(sample_capture("hybrid", seed=0).triggers)
        maps = capture.results["stored"].maps
        assert list(maps) == ["normal"] and not isinstance(maps, dict)
        np.testing.assert_array_equal(maps["normal"], stored.maps["normal"])
        np.testing.assert_array_equal(capture.triggers.t, sample_capture("hybrid", seed=0).triggers.t)
    loaded = psfmt.load(path)
    assert isinstance(loaded.results["stored"].maps, dict) and isinstance(loaded.triggers, psfmt.Triggers)


def test_item_1_limits_are_configurable(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    path = written(tmp_path)
    assert psfmt.validate(path).valid
    monkeypatch.setenv("PSFMT_MAX_ARRAY_BYTES", "40000")
    normal = "/ground_truth/albedo: holds 49,152 bytes, more than the limit of 40,000 read at once (PSFMT_MAX_ARRAY_BYTES)"
    assert [f.text for f in psfmt.validate(path).errors][:1] == [normal]
    monkeypatch.delenv("PSFMT_MAX_ARRAY_BYTES")
    frames = "/frames/data: is 64×64 pixels, more than the limit of 1,000 (PSFMT_MAX_PIXELS)"
    assert [f.text for f in psfmt.validate(path, limits=psfmt.Limits(max_pixels=1000)).errors][:1] == [frames]
    monkeypatch.setenv("PSFMT_MAX_PIXELS", "lots")
    capsys.readouterr()
    assert main(["validate", str(path)]) == 2
    assert capsys.readouterr().err == "pstoolkit: error: PSFMT_MAX_PIXELS: expected a positive integer, got 'lots'\n"


def index_claims_everything(f: h5py.File) -> None:
    """10¹¹ chunked events with no chunk written and the index [0, N] of a stream whose times all read 0."""
    for c in "xytp":
        dtype = f[f"events/{c}"].dtype
        declared(f"events/{c}", (10**11,), dtype, (1 << 16,))(f)
    del f["events/ms_to_idx"]
    f["events/ms_to_idx"] = np.array([0, 10**11], np.uint64)
    f["events"].attrs["ms_origin_us"] = 0


def test_item_2_declared_events_are_refused_at_once(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = edited(tmp_path, index_claims_everything)
    assert_refused(path, "/events/p: declares (100000000000,) int8 (100,000,000,000 bytes) but the file stores no data for it", capsys)


def test_item_2_validate_reports_progress_and_quick_reads_no_data(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = written(tmp_path)
    seen: list[float] = []
    assert psfmt.validate(path, progress=lambda fraction, message: seen.append(fraction)).valid
    assert seen == sorted(seen) and seen[-1] == 1.0 and len(seen) > 3
    with h5py.File(path, "r") as f:
        chunk = f["frames/data"].id.get_chunk_info(1)
    raw = bytearray(path.read_bytes())
    raw[chunk.byte_offset : chunk.byte_offset + chunk.size] = bytes(chunk.size)
    path.write_bytes(bytes(raw))
    quick = psfmt.validate(path, quick=True)
    assert quick.valid
    with pytest.raises(psfmt.FormatError, match="damaged HDF5 file"):
        psfmt.validate(path)
    capsys.readouterr()
    assert main(["validate", "--quick", str(path)]) == 0
    assert capsys.readouterr().out.splitlines()[-1] == f"{path}: valid ({len(quick.warnings)} warning(s)) (structure only: --quick)"
    assert main(["validate", "--json", str(path)]) == 2


def test_item_3_sensor_sizes_are_bounded(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    def huge(f: h5py.File) -> None:
        f["events"].attrs["width"] = 2**31 - 1
        f["events"].attrs["height"] = 2**31 - 1

    path = edited(tmp_path, huge)
    message = "/events: width 2147483647 exceeds 65536, the most uint16 coordinates address"
    assert [f.text for f in psfmt.validate(path).errors][:2] == [message, message.replace("width", "height")]
    capsys.readouterr()
    assert main(["run", str(path), "--solver", "eventps", "-o", str(tmp_path / "out")]) == 2
    assert capsys.readouterr().err == f"pstoolkit: error: {path}: {message}\n"
    raw = tmp_path / "huge.raw"
    raw.write_bytes(format_header("EVT3", 16, 12).replace(b"geometry 16x12", b"geometry 2000000000x2000000000") + bytes(8))
    assert main(["convert", "raw", str(raw), "-o", str(tmp_path / "huge.h5")]) == 2
    assert capsys.readouterr().err == (
        f"pstoolkit: error: {raw}: RAW header declares a 2000000000×2000000000 sensor; each side must be 1…65536 pixels\n"
    )
    assert not (tmp_path / "huge.h5").exists()


# Bit flips (byte offset, bit) of the sample capture that made h5py raise RuntimeError or KeyError
# through validate, or that validate passed and the reader found damaged, with HDF5 2.0 (the file's
# bytes depend on the HDF5 version; whatever each flip does elsewhere, the assertions hold).
FLIPS = [(7090, 6), (6209, 7), (170, 0), (6323, 6), (1290, 6), (1015, 2), (1062, 3), (1171, 3), (273684, 7), (31073, 0)]


def test_item_4_hdf5_errors_are_one_line_and_validate_agrees_with_the_reader(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    data = written(tmp_path).read_bytes()
    damaged = 0
    for pos, bit in FLIPS:
        if pos >= len(data):
            continue
        raw = bytearray(data)
        raw[pos] ^= 1 << bit
        path = tmp_path / f"flip-{pos}-{bit}.h5"
        path.write_bytes(bytes(raw))
        # validate in a child (a flipped heap can send HDF5 into a loop), then read it all here: they agree
        checked = probe(path)
        damaged += "damaged HDF5 file (" in checked
        capsys.readouterr()
        code = main(["info", str(path)])
        out, err = capsys.readouterr()
        expected = (0, "") if checked == "valid" else (2, f"pstoolkit: error: {path}: {checked.split(': ', 1)[1]}\n")
        assert (code, err) == expected, (pos, bit)
    assert damaged >= 5


def gcol_loop(path: Path) -> None:
    """Zero the first object of the file's first global heap: HDF5 2.0 decodes it for ever."""
    raw = bytearray(path.read_bytes())
    heap = raw.find(b"GCOL")
    assert heap > 0
    first = heap + 16
    raw[first : first + 2] = bytes(2)  # object index 0: free space ...
    raw[first + 8 : first + 16] = bytes(8)  # ... of size 0, so the decoder never moves on
    path.write_bytes(bytes(raw))


def test_item_4_a_file_that_hangs_hdf5_is_a_damaged_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    path = written(tmp_path)
    gcol_loop(path)
    monkeypatch.setattr(isolate, "QUIET_S", 3.0)
    with deadline(60):
        assert main(["validate", str(path)]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"pstoolkit: error: {path}: damaged HDF5 file (") and len(err.splitlines()) == 1
        assert main(["info", str(path)]) == 2
        assert capsys.readouterr().err == err


def shifted(tmp_path: Path, offset_us: int) -> Path:
    """The sample capture with every time (events, exposures, triggers, the light's t0) moved by ``offset_us``."""
    capture = sample_capture("hybrid", seed=0, n_events=3000)
    events = capture.events.read()
    capture.events.data = psfmt.EventArray(events.x, events.y, events.t + offset_us, events.p)
    capture.frames.t_start_us += offset_us
    capture.frames.t_end_us += offset_us
    capture.triggers.t += offset_us
    capture.lights.params["t0_us"] = int(capture.lights.params.get("t0_us", 0)) + offset_us
    path = tmp_path / f"shifted-{offset_us}.h5"
    psfmt.write(capture, path)
    return path


def test_item_8_times_beyond_float64_precision_are_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert psfmt.validate(shifted(tmp_path, 2**52)).valid  # Unix time in µs (2⁵⁰·⁶) and more: fine
    path = shifted(tmp_path, 2**62)
    message = "/frames/t_start_us: time 4611686018427387904 µs lies beyond ±2^53 µs (±285 years), where times stop converting to float64 exactly"
    assert_refused(path, message, capsys)
    with h5py.File(path, "r+") as f:
        del f["frames"]
    origin = "/events: ms_origin_us 4611686018427387000 µs lies beyond ±2^53 µs (±285 years), where times stop converting to float64 exactly"
    assert [f.text for f in psfmt.validate(path).errors][:1] == [origin]


def test_item_15_symbolic_link_loops_and_absurd_superblocks_are_named(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    loop = tmp_path / "loop.h5"
    os.symlink(tmp_path / "other.h5", loop)
    os.symlink(loop, tmp_path / "other.h5")
    path = written(tmp_path)
    raw = bytearray(path.read_bytes())
    assert raw[8] == 0  # superblock version 0: the end-of-file address is bytes 40-47, unchecksummed
    raw[40:48] = struct.pack("<Q", 18445618173802785403)
    path.write_bytes(bytes(raw))
    expected = {
        loop: "is a loop of symbolic links",
        path: f"damaged HDF5 file (its superblock records an end at byte 18445618173802785403; the file has {len(raw)} bytes)",
    }
    for target, message in expected.items():
        capsys.readouterr()
        assert main(["info", str(target)]) == 2
        assert capsys.readouterr().err == f"pstoolkit: error: {target}: {message}\n"
