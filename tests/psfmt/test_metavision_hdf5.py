"""Metavision HDF5 files and psfmt's ECF decoder: fixtures written by Prophesee's codec decoded bit for
bit by both engines, time windows through /CD/indexes, plain and hdf5plugin files, hostile chunks."""

from __future__ import annotations

import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

from psfmt.errors import FormatError
from psfmt.eventfiles._ecf.batch import decode_batch
from psfmt.eventfiles._ecf.chunk import OK
from psfmt.eventfiles._evt3.engine import has_numba
from psfmt.eventfiles.metavision_hdf5 import MetavisionHdf5File

DATA = Path(__file__).parent / "data" / "ecf"
ENGINES = ["numpy", pytest.param("numba", marks=pytest.mark.skipif(not has_numba(), reason="numba not installed"))]
EXTRA = {
    "/extra/edge": "edge_",
    "/extra/reused_encoder_packed": "reused_packed_",
    "/extra/reused_encoder_masked": "reused_masked_",
    "/extra/chunk1": "",
    "/extra/chunk7": "",
    "/extra/chunk1000": "",
    "/extra/chunk65535": "",
}


def expected(npz: np.lib.npyio.NpzFile, prefix: str = "", lo: int = 0, hi: int | None = None) -> dict[str, np.ndarray]:
    out = {k: npz[prefix + k][lo:hi] for k in "xyt"}
    out["p"] = 2 * npz[prefix + "p"][lo:hi].astype(np.int8) - 1
    return out


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("name", ["small", "varied"])
def test_fixture_events_bit_identical(name: str, engine: str) -> None:
    want = expected(np.load(DATA / f"{name}-events.npz"))
    with MetavisionHdf5File(DATA / f"{name}.hdf5", engine=engine, batch_events=40_000, threads=2) as f:
        assert (f.width, f.height, f.header.geometry_source) == (1280, 720, "geometry 1280x720")
        assert f.header.fields["serial_number"] == "00000000" and f.ecf
        events = f.read()
        triggers = f.triggers()
    for k in "xytp":
        assert np.array_equal(getattr(events, k), want[k]), k
    if name == "small":
        trig = np.load(DATA / "small-triggers.npz")
        assert np.array_equal(triggers.t, trig["t"]) and np.array_equal(triggers.value, trig["p"])
        assert np.array_equal(triggers.channel, trig["id"]) and len(triggers) == 10
    else:
        assert len(triggers) == 0


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("dataset", sorted(EXTRA))
def test_extra_datasets_chunk_by_chunk(dataset: str, engine: str) -> None:
    """Chunk sizes 1 … 65535, padded last chunks, 2⁶⁰ µs time jumps, x/y 2047 and a reused encoder's
    leftovers, decoded straight from the stored chunks."""
    npz = np.load(DATA / "varied-events.npz")
    with h5py.File(DATA / "varied.hdf5", "r") as f:
        ds = f[dataset]
        lo, hi = (int(v) for v in ds.attrs["source_slice"]) if "source_slice" in ds.attrs else (0, None)
        chunk = ds.chunks[0]
        raw = [ds.id.read_direct_chunk((c,))[1] for c in range(0, ds.shape[0], chunk)]
        n = ds.shape[0]
    counts = np.array([int.from_bytes(b[:4], "little") >> 2 for b in raw])
    x, y, t, p, status = decode_batch(raw, counts, 2048, 2048, engine, threads=2)
    assert (status == OK).all()
    want = expected(npz, EXTRA[dataset], lo, hi)
    for k, got in zip("xytp", (x, y, t, p)):
        assert np.array_equal(got[:n], want[k][:n]), k
    if dataset == "/extra/edge":
        assert int(t[:n].max()) - int(t[:n].min()) >= 1 << 60 and int(x.max()) == 2047


def test_indexes_and_time_windows() -> None:
    npz = np.load(DATA / "varied-events.npz")
    t = npz["t"]
    with h5py.File(DATA / "varied.hdf5", "r") as f:
        idx = f["/CD/indexes"][()]
        offset = int(f["/CD/indexes"].attrs["offset"])
    ids, ts = idx["id"][1:].astype(np.int64), idx["ts"][1:] - offset
    assert offset == -int(t[0]) and (t[ids] == ts).all() and (t[ids[ids > 0] - 1] < ts[ids > 0]).all()
    with MetavisionHdf5File(DATA / "varied.hdf5", engine="numpy", batch_events=16384) as f:
        assert f.start_event(int(t[70_000])) > 60_000  # decoding starts near the window, not at 0
        for a, b in [(0, 1), (500, 9000), (65_000, 70_000), (99_990, 100_002)]:
            t0, t1 = int(t[a]), int(t[b])
            window = f.window(t0, t1)
            keep = (t >= t0) & (t < t1)
            assert np.array_equal(window.t, t[keep]) and np.array_equal(window.x, npz["x"][keep])
        assert len(f.window(int(t[-1]) + 1, int(t[-1]) + 10)) == 0


def plain_copy(path: Path, **filters: object) -> Path:
    """small.hdf5 with /CD/events rewritten uncompressed or through another filter."""
    src = DATA / "small.hdf5"
    with h5py.File(src, "r") as f, h5py.File(path, "w") as g:
        for k, v in f.attrs.items():
            g.attrs[k] = v
        npz = np.load(DATA / "small-events.npz")
        events = np.empty(len(npz["t"]), f["/CD/events"].dtype)
        for k in "xypt":
            events[k] = npz[k]
        g.create_dataset("/CD/events", data=events, chunks=(4096,), maxshape=(None,), **filters)
        f.copy("/EXT_TRIGGER", g)
        f.copy("/CD/indexes", g["/CD"])
    return path


@pytest.mark.parametrize("filters", [{}, {"compression": "gzip"}, "zstd"])
def test_uncompressed_and_other_filters(tmp_path: Path, filters: dict[str, object] | str) -> None:
    if filters == "zstd":
        hdf5plugin = pytest.importorskip("hdf5plugin")
        filters = dict(hdf5plugin.Zstd())
    path = plain_copy(tmp_path / "plain.hdf5", **filters)
    want = expected(np.load(DATA / "small-events.npz"))
    with MetavisionHdf5File(path, batch_events=5000) as f:
        assert not f.ecf
        events = f.read()
        window = f.window(int(want["t"][3000]), int(want["t"][7000]))
    for k in "xytp":
        assert np.array_equal(getattr(events, k), want[k])
    t0, t1 = want["t"][3000], want["t"][7000]
    assert np.array_equal(window.t, want["t"][(want["t"] >= t0) & (want["t"] < t1)])


def rewrite_chunk(path: Path, offset: int, edit: object) -> None:
    with h5py.File(path, "r+") as f:
        ds = f["/CD/events"]
        mask, data = ds.id.read_direct_chunk((offset,))
        ds.id.write_direct_chunk((offset,), edit(bytearray(data)), mask)  # type: ignore[operator]


def _count(data: bytearray, n: int) -> bytes:
    data[:4] = (n << 2 | (data[0] & 3)).to_bytes(4, "little")
    return bytes(data)


HOSTILE = {
    "truncated": (16384, lambda d: bytes(d[: len(d) // 2]), "chunk 1 (events 16,384…) ends before the events its header counts"),
    "count beyond chunk": (0, lambda d: _count(d, 20000), "chunk 0's header counts 20,000 events, more than its chunk of 16,384 holds"),
    "count inflated": (16384, lambda d: _count(d, 3700), "chunk 1 (events 16,384…) "),
    "time back": (16384, lambda d: bytes(d[:4] + (0).to_bytes(8, "little") + d[12:]), "time goes back from chunk 0 to chunk 1"),
}


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("case", sorted(HOSTILE))
def test_hostile_chunks_one_line(tmp_path: Path, case: str, engine: str) -> None:
    path = tmp_path / "bad.hdf5"
    shutil.copy(DATA / "small.hdf5", path)
    offset, edit, message = HOSTILE[case]
    rewrite_chunk(path, offset, edit)
    with MetavisionHdf5File(path, engine=engine) as f, pytest.raises(FormatError) as err:
        f.read()
    text = str(err.value)
    assert text.startswith(f"{path}: /CD/events") and message in text and "\n" not in text


@pytest.mark.parametrize("engine", ENGINES)
def test_coordinates_beyond_geometry(tmp_path: Path, engine: str) -> None:
    path = tmp_path / "small.hdf5"
    shutil.copy(DATA / "small.hdf5", path)
    with h5py.File(path, "r+") as f:
        f.attrs["geometry"], f.attrs["format"] = "640x480", "EVT3;height=480;width=640"
    with MetavisionHdf5File(path, engine=engine) as f, pytest.raises(FormatError, match="has events outside the sensor geometry"):
        f.read()
    with MetavisionHdf5File(path, engine=engine, geometry=(1280, 720)) as f:
        assert len(f.read()) == 20000


def test_not_metavision(tmp_path: Path) -> None:
    path = tmp_path / "other.h5"
    with h5py.File(path, "w") as f:
        f["events/x"] = np.zeros(3)
    with pytest.raises(FormatError, match=r"not a Metavision HDF5 event file \(no /CD/events dataset\)"):
        MetavisionHdf5File(path)
    shutil.copy(DATA / "small.hdf5", path)
    with h5py.File(path, "r+") as f:
        del f.attrs["geometry"], f.attrs["format"], f.attrs["system_ID"], f.attrs["generation"], f.attrs["sensor_generation"]
    with pytest.raises(FormatError, match="declares no sensor geometry"):
        MetavisionHdf5File(path)


@pytest.mark.skipif(not has_numba(), reason="numba not installed")
def test_engines_agree_on_damaged_chunks() -> None:
    """Random byte changes, cuts and counts (seeded) in chunks of every mode: the compiled loop and
    the numpy path accept the same chunks and decode them alike, and never read past a chunk."""
    with h5py.File(DATA / "varied.hdf5", "r") as f:
        ds = f["/extra/chunk1000"]
        chunks = [ds.id.read_direct_chunk((c,))[1] for c in range(0, 7000, 1000)]
    rng = np.random.default_rng(7)
    accepted = refused = 0
    for k in range(300):
        data = bytearray(chunks[k % len(chunks)])
        n = int.from_bytes(data[:4], "little") >> 2
        kind = k % 3
        if kind == 0:
            for at in rng.integers(4, len(data), 3):
                data[at] = int(rng.integers(0, 256))
        elif kind == 1:
            data = data[: int(rng.integers(4, len(data)))]
        else:
            n = int(rng.integers(1, 1200))
            data[:4] = (n << 2 | (data[0] & 3)).to_bytes(4, "little")
        got = [decode_batch([bytes(data)], np.array([n]), 1280, 720, engine) for engine in ("numba", "numpy")]
        ok = [int(g[4][0]) == OK for g in got]
        assert ok[0] == ok[1], k
        if ok[0]:
            accepted += 1
            assert all(np.array_equal(a, b) for a, b in zip(got[0][:4], got[1][:4])), k
        else:
            refused += 1
    assert accepted > 10 and refused > 100


def test_damaged_index_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "small.hdf5"
    shutil.copy(DATA / "small.hdf5", path)
    with h5py.File(path, "r+") as f:
        idx = f["/CD/indexes"]
        table = idx[()]
        table["id"][5] = 10**9
        idx[...] = table
    with MetavisionHdf5File(path) as f, pytest.raises(FormatError, match="/CD/indexes is not an increasing index into the 20,000 events"):
        f.window(1000, 2000)
