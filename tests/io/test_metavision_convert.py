"""``convert hdf5``: a Metavision HDF5 recording (ECF fixture) with frames timed by its triggers → a capture."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest

import psfmt
from pstoolkit.cli import main

DATA = Path(__file__).parents[1] / "psfmt" / "data" / "ecf"


def test_convert_hdf5_with_frames_round_trips(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    trig = np.load(DATA / "small-triggers.npz")
    rising = trig["t"][trig["p"] == 1]
    folder = tmp_path / "frames"
    folder.mkdir()
    rgb = np.random.default_rng(0).integers(0, 256, (len(rising), 8, 10, 3), dtype=np.uint8)
    for k in range(len(rising)):
        cv2.imwrite(str(folder / f"frame_{k:03d}.png"), rgb[k][..., ::-1])
    out = tmp_path / "capture.h5"
    assert main(["convert", "hdf5", str(DATA / "small.hdf5"), "-o", str(out), "--frames", str(folder)]) == 0
    assert capsys.readouterr().out == f"wrote {out}\n"
    want = np.load(DATA / "small-events.npz")
    with psfmt.read(out) as capture:
        events = capture.events.read()
        assert (capture.events.width, capture.events.height) == (1280, 720)
        assert np.array_equal(events.x, want["x"]) and np.array_equal(events.y, want["y"])
        assert np.array_equal(events.t, want["t"]) and np.array_equal(events.p, 2 * want["p"] - 1)
        assert np.array_equal(capture.triggers.t, trig["t"]) and np.array_equal(capture.triggers.value, trig["p"])
        assert np.array_equal(np.asarray(capture.frames.data), rgb)
        assert capture.frames.t_start_us.tolist() == rising.tolist()
        assert capture.frames.t_end_us.tolist() == trig["t"][trig["p"] == 0].tolist()
        assert "geometry_source = geometry 1280x720" in capture.description
    assert psfmt.validate(out).valid


def test_convert_hdf5_hostile_chunk_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src = tmp_path / "cut.hdf5"
    shutil.copy(DATA / "small.hdf5", src)
    with h5py.File(src, "r+") as f:
        ds = f["/CD/events"]
        mask, data = ds.id.read_direct_chunk((0,))
        ds.id.write_direct_chunk((0,), data[:100], mask)
    out = tmp_path / "out.h5"
    assert main(["convert", "hdf5", str(src), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert err == f"pstoolkit: error: {src}: /CD/events: chunk 0 (events 0…) ends before the events its header counts\n"
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["cut.hdf5"]
