"""Every listed fault is caught with its one-line message, through the API and through the CLI.

Faulty files are made by writing a valid capture and breaking it with h5py (or by cutting its bytes).
Three tiers: ``open`` (the file cannot be read at all: FormatError, exit 2 from both commands),
``structure`` (metadata or shapes break the spec: the reader refuses, validate exits 1) and ``content``
(found by scanning the data: lazy reads still work, ``read(verify=True)`` refuses, validate exits 1).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np
import pytest
from helpers.captures import sample_capture

import psfmt
from pstoolkit.cli import main


def written(tmp_path: Path, kind: str = "hybrid", **kwargs: object) -> Path:
    path = tmp_path / "capture.h5"
    psfmt.write(sample_capture(kind, seed=0, n_events=3000, **kwargs), path)
    return path


def broken(edit: Callable[[h5py.File], None], kind: str = "hybrid", **kwargs: object) -> Callable[[Path], Path]:
    """A file maker: write a valid capture of ``kind``, then apply ``edit`` to it in place."""

    def make(tmp_path: Path) -> Path:
        path = written(tmp_path, kind, **kwargs)
        with h5py.File(path, "r+") as f:
            edit(f)
        return path

    return make


def replace(name: str, make: Callable[[np.ndarray], np.ndarray]) -> Callable[[h5py.File], None]:
    """An edit that rewrites dataset ``name`` as ``make(old values)``."""

    def edit(f: h5py.File) -> None:
        values = make(f[name][()])
        del f[name]
        f.create_dataset(name, data=values)

    return edit


def poke(name: str, index: int, value: float) -> Callable[[h5py.File], None]:
    def edit(f: h5py.File) -> None:
        f[name][index] = value

    return edit


def setattr_(name: str, key: str, value: object) -> Callable[[h5py.File], None]:
    def edit(f: h5py.File) -> None:
        f[name].attrs[key] = value

    return edit


def swap_times(f: h5py.File) -> None:
    t = f["events/t"]
    t[17], t[18] = int(t[18]), int(t[17])


def sampled_with_times(times_us: list[int], **attrs: object) -> Callable[[h5py.File], None]:
    """An edit that turns the ring light into a sampled trajectory with the given sample times."""

    def edit(f: h5py.File) -> None:
        del f["lights"]
        g = f.create_group("lights")
        g.attrs["model"] = "sampled"
        g.attrs["periodic"] = False
        g["times_us"] = np.asarray(times_us, np.int64)
        g["directions"] = np.tile([0.0, 0.0, 1.0], (len(times_us), 1))
        g["intensities"] = np.ones((len(times_us), 3))
        g.attrs.update(attrs)

    return edit


def missing(tmp_path: Path) -> Path:
    return tmp_path / "nowhere.h5"


def folder(tmp_path: Path) -> Path:
    (tmp_path / "dir.h5").mkdir()
    return tmp_path / "dir.h5"


def not_hdf5(tmp_path: Path) -> Path:
    path = tmp_path / "notes.h5"
    path.write_text("x y t p\n1 2 3 1\n")
    return path


def truncated(tmp_path: Path) -> Path:
    path = written(tmp_path)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    return path


def not_a_capture(tmp_path: Path) -> Path:
    path = tmp_path / "other.h5"
    with h5py.File(path, "w") as f:
        f["events/t"] = np.arange(3)
    return path


@dataclass
class Fault:
    tier: str
    make: Callable[[Path], Path]
    message: str


FAULTS: dict[str, Fault] = {
    "missing path": Fault("open", missing, "no such file"),
    "folder": Fault("open", folder, "is a folder, not a capture file"),
    "not HDF5": Fault("open", not_hdf5, "not an HDF5 file"),
    "truncated": Fault("open", truncated, "truncated HDF5 file ({half} of {size} bytes present)"),
    "not a capture": Fault("open", not_a_capture, "/: not a hybrid-capture file (root attribute 'format' is None)"),
    "newer major version": Fault(
        "open", broken(lambda f: f.attrs.__setitem__("format_version", "2.0")),
        "/: format_version 2.0 is newer than this reader supports (1.x); update psfmt",
    ),
    "version not MAJOR.MINOR": Fault(
        "open", broken(lambda f: f.attrs.__setitem__("format_version", "1")), "/: format_version '1' is not MAJOR.MINOR"
    ),
    "missing event column": Fault("structure", broken(lambda f: f.__delitem__("events/t")), "/events: dataset 't' is missing"),
    "missing frame data": Fault("structure", broken(lambda f: f.__delitem__("frames/data")), "/frames: dataset 'data' is missing"),
    "frames of wrong shape": Fault(
        "structure", broken(replace("frames/data", lambda a: a.reshape(3, 64, 192))),
        "/frames/data: has shape (3, 64, 192), expected (K, H, W, C)",
    ),
    "ground truth of wrong size": Fault(
        "structure", broken(replace("ground_truth/normal", lambda a: a[:32])),
        "/ground_truth/normal: is 32×64, but the frames are 64×64",
    ),
    "affine of wrong shape": Fault(
        "structure", broken(replace("calibration/event_to_frame", lambda a: np.eye(3))),
        "/calibration/event_to_frame: has shape (3, 3), expected (2, 3)",
    ),
    "event column of wrong dtype": Fault(
        "structure", broken(replace("events/x", lambda a: a.astype(np.int32))), "/events/x: has dtype int32, expected uint16"
    ),
    "frames of wrong dtype": Fault(
        "structure", broken(replace("frames/data", lambda a: a.astype(np.int16))),
        "/frames/data: has dtype int16, expected uint8, uint16 or float32",
    ),
    "columns of unequal length": Fault(
        "structure", broken(replace("events/p", lambda a: a[:-1])), "/events: columns x, y, t, p differ in length ([2999, 3000])"
    ),
    "exposure ends before it starts": Fault(
        "structure", broken(poke("frames/t_end_us", 1, 0)), "/frames: exposure window of frame 1 ends before it starts"
    ),
    "light model parameter missing": Fault(
        "structure", broken(lambda f: f["lights"].attrs.__delitem__("period_us")), "/lights: parameter 'period_us' is missing"
    ),
    "sense not ±1": Fault("structure", broken(setattr_("lights", "sense", 0)), "/lights: sense must be +1 or -1, got 0"),
    "unknown refractory rule": Fault(
        "structure", broken(setattr_("calibration", "refractory_rule", "reset-\x1b[2Jlater")),
        "/calibration: refractory_rule 'reset-\\x1b[2Jlater' is not one of reset-at-end, rate-limited",
    ),
    "ms index missing": Fault(
        "structure", broken(lambda f: f.__delitem__("events/ms_to_idx")),
        "/events: the millisecond index (ms_to_idx, ms_origin_us) is missing",
    ),
    "ms index of wrong length": Fault(
        "structure", broken(replace("events/ms_to_idx", lambda a: a[:5])),
        "/events/ms_to_idx: has shape (5,), expected (31,) for the stored times",
    ),
    "unsorted events": Fault("content", broken(swap_times), "/events/t: events are not sorted by time (event 18 goes back)"),
    "polarity 0": Fault("content", broken(poke("events/p", 5, 0)), "/events/p: polarity of event 5 is 0, not ±1"),
    "x outside the sensor": Fault(
        "content", broken(poke("events/x", 7, 40)), "/events/x: event 7 has x = 40, outside the 32×32 sensor"
    ),
    "NaN in frames": Fault(
        "content", broken(poke("frames/data", (1, 3, 4, 0), np.nan), kind="frames", dtype=np.float32),
        "/frames/data: frame 1 holds NaN or infinite values",
    ),
    "inf in frames": Fault(
        "content", broken(poke("frames/data", (4, 0, 0, 2), np.inf), kind="frames", dtype=np.float32),
        "/frames/data: frame 4 holds NaN or infinite values",
    ),
    "ms index does not match": Fault(
        "content", broken(poke("events/ms_to_idx", 3, 7)), "/events/ms_to_idx: does not match the event times (rebuild the index)"
    ),
    "ms origin does not match": Fault(
        "content", broken(setattr_("events", "ms_origin_us", 1000)),
        "/events/ms_to_idx: does not match the event times (rebuild the index)",
    ),
    "sampled times not increasing": Fault(
        "content", broken(sampled_with_times([0, 5, 5])), "/lights/times_us: sample times are not strictly increasing"
    ),
    "sampled samples span a period": Fault(
        "content", broken(sampled_with_times([0, 5, 10], periodic=True, period_us=10)),
        "/lights/times_us: samples span 10 µs, not less than period_us 10",
    ),
    "sampled periodic without period": Fault(
        "structure", broken(sampled_with_times([0, 5, 10], periodic=True)),
        "/lights: a periodic sampled trajectory needs 'period_us'",
    ),
    "sampled aperiodic with period": Fault(
        "structure", broken(sampled_with_times([0, 5, 10], period_us=20)),
        "/lights: a non-periodic sampled trajectory must not have 'period_us'",
    ),
    "sampled interpolation unknown": Fault(
        "structure", broken(sampled_with_times([0, 5, 10], interpolation="cubic")),
        "/lights: interpolation 'cubic' is not defined in format 1.3 (only 'linear-renormalised')",
    ),
}


@pytest.mark.parametrize("name", FAULTS)
def test_fault_is_caught_with_its_message(tmp_path: Path, name: str, capsys: pytest.CaptureFixture[str]) -> None:
    fault = FAULTS[name]
    path = fault.make(tmp_path)
    message = fault.message
    if name == "truncated":
        message = message.format(half=path.stat().st_size, size=len(whole_capture_bytes(tmp_path)))
    line = f"{path}: {message}"

    if fault.tier in ("open", "structure"):
        with pytest.raises(psfmt.FormatError) as caught:
            psfmt.read(path)
        assert str(caught.value) == line
    else:
        with psfmt.read(path) as lazy:
            assert lazy.kind in ("hybrid", "frames")
        for reader in (lambda: psfmt.read(path, verify=True), lambda: psfmt.load(path)):
            with pytest.raises(psfmt.FormatError) as caught:
                reader()
            assert str(caught.value) == line

    if fault.tier == "open":
        with pytest.raises(psfmt.FormatError) as caught:
            psfmt.validate(path)
        assert str(caught.value) == line
    else:
        report = psfmt.validate(path)
        assert not report.valid
        assert [f.text for f in report.errors] == [message]

    capsys.readouterr()
    assert main(["info", str(path)]) == 2
    out, err = capsys.readouterr()
    assert (out, err) == ("", f"pstoolkit: error: {line}\n")

    code = main(["validate", str(path)])
    out, err = capsys.readouterr()
    if fault.tier == "open":
        assert (code, out, err) == (2, "", f"pstoolkit: error: {line}\n")
    else:
        assert code == 1 and err == ""
        assert [x for x in out.splitlines() if ": error: " in x] == [f"{path}: error: {message}"]
        assert "valid (" not in out


def whole_capture_bytes(tmp_path: Path) -> bytes:
    """The bytes of the capture the truncated file was cut from (the writer is deterministic)."""
    other = tmp_path / "whole"
    other.mkdir()
    return written(other).read_bytes()


def test_newer_minor_version_and_unknown_parts_only_warn(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = written(tmp_path)
    with h5py.File(path, "r+") as f:
        f.attrs["format_version"] = "1.4"
        f.attrs["future_attribute"] = 3
        f["future_group/data"] = np.arange(4)
        f["events"].attrs["future_rate_hz"] = 1.5
    report = psfmt.validate(path)
    assert report.errors == []
    assert [w.text for w in report.warnings] == [
        "/: written by format 1.4, newer than 1.3: parts this reader does not know are ignored"
    ]
    with psfmt.read(path, verify=True) as capture:
        assert capture.format_version == "1.4" and len(capture.events) == 3000
    assert main(["validate", str(path)]) == 0
    out, err = capsys.readouterr()
    assert err == ""
    assert out.splitlines() == [
        f"{path}: warning: /: written by format 1.4, newer than 1.3: parts this reader does not know are ignored",
        f"{path}: valid (1 warning(s))",
    ]


def test_valid_file_passes_with_its_warnings(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = written(tmp_path)
    with h5py.File(path, "r+") as f:
        del f["ground_truth"]
        del f["calibration"].attrs["contrast_pos"]
    assert main(["validate", str(path)]) == 0
    out, err = capsys.readouterr()
    assert err == ""
    assert out.splitlines() == [
        f"{path}: warning: /calibration: contrast thresholds are unknown; solvers fall back to their defaults",
        f"{path}: warning: /: no ground truth: accuracy cannot be measured",
        f"{path}: valid (2 warning(s))",
    ]


def test_cli_errors_carry_no_traceback(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = FAULTS["newer major version"].make(tmp_path)
    for command in ("info", "validate"):
        assert main([command, str(path)]) == 2
        out, err = capsys.readouterr()
        assert "Traceback" not in out + err and len(err.splitlines()) == 1


def test_damaged_chunk_is_a_one_line_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = written(tmp_path)
    with h5py.File(path, "r") as f:
        chunk = f["frames/data"].id.get_chunk_info(1)
    raw = bytearray(path.read_bytes())
    raw[chunk.byte_offset : chunk.byte_offset + chunk.size] = bytes(chunk.size)
    path.write_bytes(bytes(raw))
    line = f"{path}: damaged HDF5 file (filter returned failure during read)"
    with psfmt.read(path) as lazy:
        np.testing.assert_array_equal(lazy.frames.frame(0), sample_capture("hybrid", seed=0).frames.data[0])
    for check in (lambda: psfmt.read(path, verify=True), lambda: psfmt.validate(path)):
        with pytest.raises(psfmt.FormatError) as caught:
            check()
        assert str(caught.value) == line
    capsys.readouterr()
    for command in ("info", "validate"):
        assert main([command, str(path)]) == 2
        assert capsys.readouterr() == ("", f"pstoolkit: error: {line}\n")
