"""Rows of event columns inflated by ISA-L (``psfmt.inflate``) against h5py's own reads."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest

from psfmt import deflate, inflate
from psfmt.deflate import ISAL_LEVEL, ChunkCompressor
from psfmt.inflate import ColumnReader

pytestmark = pytest.mark.skipif(deflate.isal_zlib is None, reason="isal is not installed")

CHUNK = 4096
ROWS = 5 * CHUNK + 123


def _columns(path: Path) -> dict[str, np.ndarray]:
    """Columns of every event dtype, in datasets of CHUNK rows: compressed by ``ChunkCompressor``
    (ISA-L's streams), by HDF5's filter at the format's level and at another, one chunk of it never
    written, and one without filters."""
    rng = np.random.default_rng(3)
    data = {
        "t": np.sort(rng.integers(0, 10**9, ROWS)).astype(np.int64),
        "x": rng.integers(0, 1280, ROWS).astype(np.uint16),
        "p": rng.choice(np.array([-1, 1], np.int8), ROWS),
    }
    options = {"chunks": (CHUNK,), "compression": "gzip", "shuffle": True}
    with h5py.File(path, "w") as f:
        compressor = ChunkCompressor(threads=2)
        for name, values in data.items():
            ours = f.create_dataset(f"ours_{name}", shape=values.shape, dtype=values.dtype,
                                    compression_opts=ISAL_LEVEL, **options)
            compressor.write(ours, values)
            f.create_dataset(f"hdf5_{name}", data=values, compression_opts=ISAL_LEVEL, **options)
            f.create_dataset(f"level4_{name}", data=values, compression_opts=4, **options)
            f.create_dataset(f"plain_{name}", data=values)
        holes = f.create_dataset("holes", shape=(ROWS,), dtype=np.int64, compression_opts=ISAL_LEVEL, **options)
        holes[: 2 * CHUNK] = data["t"][: 2 * CHUNK]
        holes[3 * CHUNK :] = data["t"][3 * CHUNK :]
        compressor.flush()
        compressor.close()
    return data


def test_any_rows_read_as_h5py_reads_them(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Whole columns, single chunks, rows across chunk edges and the padded last chunk read equal to
    h5py's slices, in every dataset; the shuffle + deflate ones are inflated by ISA-L (a chunk never
    written reads as HDF5 fills it), the others through h5py."""
    _columns(tmp_path / "a.h5")
    inflated = []
    real = deflate.isal_zlib.decompress
    monkeypatch.setattr(inflate.isal_zlib, "decompress", lambda *a, **k: inflated.append(1) or real(*a, **k))
    spans = [(0, ROWS), (0, 1), (CHUNK - 1, CHUNK + 1), (CHUNK, 2 * CHUNK), (ROWS - 5, ROWS), (7, 7), (100, 3 * CHUNK + 9)]
    rng = np.random.default_rng(0)
    spans += [tuple(sorted(int(i) for i in rng.integers(0, ROWS + 1, 2))) for _ in range(40)]
    with h5py.File(tmp_path / "a.h5", "r") as f:
        for name, ds in f.items():
            reader = ColumnReader(ds)
            fast = name.startswith(("ours", "hdf5", "level4", "holes"))
            assert (reader._chunk == CHUNK) == fast, name
            for lo, hi in spans:
                before = len(inflated)
                rows = reader.read(lo, hi)
                assert rows.dtype == ds.dtype and rows.shape == (hi - lo,)
                np.testing.assert_array_equal(rows, ds[lo:hi], err_msg=f"{name}[{lo}:{hi}]")
                hole = name == "holes" and lo < 3 * CHUNK and hi > 2 * CHUNK
                assert (len(inflated) > before) == (fast and hi > lo and not hole), (name, lo, hi)


def test_without_isal_rows_are_read_through_h5py(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    data = _columns(tmp_path / "a.h5")
    monkeypatch.setattr(inflate, "isal_zlib", None)
    with h5py.File(tmp_path / "a.h5", "r") as f:
        reader = ColumnReader(f["ours_t"])
        assert reader._chunk == 0
        np.testing.assert_array_equal(reader.read(10, 3 * CHUNK), data["t"][10 : 3 * CHUNK])


def test_a_chunk_that_does_not_inflate_is_read_through_h5py(tmp_path: Path) -> None:
    """A damaged chunk gives HDF5's own error, not ISA-L's; the chunks around it still read."""
    data = _columns(tmp_path / "a.h5")
    path = tmp_path / "a.h5"
    with h5py.File(path, "r") as f:
        info = f["ours_t"].id.get_chunk_info(2)
    raw = bytearray(path.read_bytes())
    raw[info.byte_offset : info.byte_offset + info.size] = bytes(info.size)
    path.write_bytes(bytes(raw))
    with h5py.File(path, "r") as f:
        reader = ColumnReader(f["ours_t"])
        np.testing.assert_array_equal(reader.read(5, 2 * CHUNK), data["t"][5 : 2 * CHUNK])
        with pytest.raises(OSError, match="filter returned failure during read"):
            reader.read(0, ROWS)
