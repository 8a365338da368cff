"""Chunks compressed in worker threads (``psfmt.deflate``) against HDF5's own shuffle + deflate."""

from __future__ import annotations

import zlib
from pathlib import Path

import h5py
import numpy as np
import pytest

from psfmt import deflate
from psfmt.deflate import ISAL_LEVEL, ChunkCompressor, deflate_chunk

CASES = [
    (np.int64, (70_000,), (16_384,)),
    (np.uint16, (70_000,), (16_384,)),
    (np.int8, (70_000,), (16_384,)),
    (np.float32, (3, 37, 50, 3), (1, 16, 50, 3)),
]


@pytest.mark.parametrize(("level", "isal"), [(ISAL_LEVEL, True), (ISAL_LEVEL, False), (4, True)])
@pytest.mark.parametrize(("dtype", "shape", "chunks"), CASES)
def test_threaded_chunks_read_back_as_hdf5_stores_them(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, dtype: type, shape: tuple, chunks: tuple, level: int,
    isal: bool,
) -> None:
    """Every chunk, edge chunks included, reads back equal through HDF5, and inflates to the bytes
    HDF5's shuffle filter makes (but for the zero padding of edge chunks, which HDF5 leaves
    unspecified); ISA-L's streams are within 20 % of zlib's size, and without ISA-L (not installed,
    or another level) the chunks are byte for byte what HDF5's filters write."""
    if not isal:
        monkeypatch.setattr(deflate, "isal_zlib", None)
    rng = np.random.default_rng(0)
    data = np.sort(rng.integers(0, 1 << 20, size=shape), axis=0).astype(dtype)
    options = {"chunks": chunks, "compression": "gzip", "compression_opts": level, "shuffle": True}
    with h5py.File(tmp_path / "a.h5", "w") as f:
        f.create_dataset("hdf5", data=data, **options)
        ours = f.create_dataset("ours", shape=shape, dtype=dtype, **options)
        compressor = ChunkCompressor(threads=3)
        compressor.write(ours, data)
        compressor.flush()
        compressor.close()
    with h5py.File(tmp_path / "a.h5", "r") as f:
        np.testing.assert_array_equal(f["ours"][...], data)
        grid = [range(0, n, c) for n, c in zip(shape, chunks)]
        whole, sizes = 0, np.zeros(2)
        for corner in np.stack(np.meshgrid(*grid, indexing="ij"), -1).reshape(-1, len(shape)):
            offset = tuple(int(c) for c in corner)
            mask, raw = f["ours"].id.read_direct_chunk(offset)
            assert mask == 0
            if all(o + c <= n for o, c, n in zip(offset, chunks, shape)):
                reference = f["hdf5"].id.read_direct_chunk(offset)[1]
                assert zlib.decompress(raw) == zlib.decompress(reference)
                if not (isal and level == ISAL_LEVEL):
                    assert raw == reference
                sizes += len(raw), len(reference)
                whole += 1
        assert whole >= 2
        assert sizes[0] < 1.2 * sizes[1]


def test_blocks_go_on_at_a_chunk_boundary_and_the_caller_may_reuse_its_array(tmp_path: Path) -> None:
    """Blocks written one after another read back whole; an array written with copies may be refilled
    at once, one written without (``copy=False``) is compressed from where it lies."""
    chunk = 1000
    with h5py.File(tmp_path / "a.h5", "w") as f:
        ds = f.create_dataset("t", shape=(0,), maxshape=(None,), dtype=np.int64, chunks=(chunk,),
                              compression="gzip", compression_opts=1, shuffle=True)
        compressor = ChunkCompressor(threads=2)
        buffer = np.arange(3 * chunk, dtype=np.int64)
        for block in range(3):
            ds.resize((block + 1) * 3 * chunk, axis=0)
            compressor.write(ds, buffer, block * 3 * chunk)
            buffer += 3 * chunk  # the next block, in the same array
        ds.resize(ds.shape[0] + 10, axis=0)
        compressor.write(ds, np.arange(10) + 9 * chunk, 9 * chunk, copy=False)
        with pytest.raises(ValueError, match="not aligned"):
            compressor.write(ds, np.arange(10), 5)
        compressor.flush()
        compressor.close()
    with h5py.File(tmp_path / "a.h5", "r") as f:
        np.testing.assert_array_equal(f["t"][...], np.arange(9 * chunk + 10))


def test_datasets_with_other_filters_are_written_through_hdf5(tmp_path: Path) -> None:
    data = np.arange(5000, dtype=np.float32)
    with h5py.File(tmp_path / "a.h5", "w") as f:
        checked = f.create_dataset("checked", shape=data.shape, dtype=data.dtype, chunks=(1024,),
                                   compression="gzip", shuffle=True, fletcher32=True)
        plain = f.create_dataset("plain", shape=data.shape, dtype=data.dtype)
        compressor = ChunkCompressor()
        compressor.write(checked, data)
        compressor.write(plain, data)
        compressor.close()
    with h5py.File(tmp_path / "a.h5", "r") as f:
        np.testing.assert_array_equal(f["checked"][...], data)
        np.testing.assert_array_equal(f["plain"][...], data)


def test_an_edge_chunk_is_padded_to_the_whole_chunk() -> None:
    block = np.arange(6, dtype=np.uint16).reshape(2, 3)
    padded = np.zeros((4, 3), np.uint16)
    padded[:2] = block
    assert deflate_chunk(block, (4, 3), 1) == deflate_chunk(padded, (4, 3), 1)
