"""Issue 33, item 14: a capture of many tiny frames. The writer puts frames under ``SMALL_CHUNK_BYTES``
into shared chunks of about ``SMALL_FRAMES_CHUNK_BYTES`` (a 1×1 frame is no 3-byte chunk), and the validator refuses a
dataset cut into more than ``MAX_SMALL_CHUNKS`` small chunks, whose reading would cost HDF5 kilobytes of
bookkeeping per chunk (10⁶ chunks: 6.5 GB), in one line from ``validate --quick`` on."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest
from helpers.captures import sample_capture

import psfmt
from psfmt.limits import MAX_SMALL_CHUNKS, SMALL_CHUNK_BYTES
from psfmt.writer import SMALL_FRAMES_CHUNK_BYTES
from pstoolkit.cli import main

N_FRAMES = 100_000


def test_the_writer_chunks_tiny_frames_together(tmp_path: Path) -> None:
    path = tmp_path / "tiny.h5"
    values = np.random.default_rng(0).integers(0, 256, (N_FRAMES, 1, 1, 3), dtype=np.uint8)
    with psfmt.CaptureWriter(path) as writer:
        writer.begin_frames(1, 1, 3, np.uint8)
        for start in range(0, N_FRAMES, 7919):  # blocks that never meet a chunk's edge
            stop = min(start + 7919, N_FRAMES)
            writer.append_frames(values[start:stop], t_start_us=np.arange(start, stop) * 10, t_end_us=np.arange(start, stop) * 10 + 5)
    with h5py.File(path) as fh:
        data = fh["frames/data"]
        assert data.chunks[0] == SMALL_FRAMES_CHUNK_BYTES // 3
        assert data.id.get_num_chunks() == -(-N_FRAMES // data.chunks[0])
    assert psfmt.validate(path).errors == []
    with psfmt.read(path, verify=True) as capture:
        assert np.array_equal(capture.frames.data[:], values)
    big = tmp_path / "big.h5"  # a frame of 4 KiB or more keeps chunks of its own: read without the others
    capture = sample_capture("frames")
    assert capture.frames.data[0].nbytes >= SMALL_CHUNK_BYTES
    psfmt.write(capture, big)
    with h5py.File(big) as fh:
        assert fh["frames/data"].chunks[0] == 1


def test_a_dataset_of_many_tiny_chunks_is_refused_in_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    good = tmp_path / "good.h5"
    with psfmt.CaptureWriter(good) as writer:
        n = MAX_SMALL_CHUNKS + 1
        writer.append_frames(np.zeros((n, 1, 1, 3), np.uint8), t_start_us=np.arange(n) * 10, t_end_us=np.arange(n) * 10 + 5)
    crafted = tmp_path / "crafted.h5"
    with h5py.File(good) as src, h5py.File(crafted, "w") as dst:
        for key, value in src.attrs.items():
            dst.attrs[key] = value
        for name in src:
            if name != "frames":
                src.copy(name, dst)
        frames = dst.create_group("frames")
        for key, value in src["frames"].attrs.items():
            frames.attrs[key] = value
        frames.create_dataset("data", data=src["frames/data"][:], chunks=(1, 1, 1, 3))  # the old writer's chunks
    line = f"/frames/data: is cut into {MAX_SMALL_CHUNKS + 1:,} chunks of 3 bytes; at most {MAX_SMALL_CHUNKS:,} chunks under {SMALL_CHUNK_BYTES:,} bytes"
    capsys.readouterr()
    assert main(["validate", "--quick", str(crafted)]) == 1
    assert line in capsys.readouterr().out
    for command in ("info", "validate"):
        code = main([command, str(crafted)])
        err = capsys.readouterr().err
        assert code == (2 if command == "info" else 1)
        assert command == "validate" or (line in err and len(err.strip().splitlines()) == 1)
    assert main(["validate", "--quick", str(good)]) == 0
