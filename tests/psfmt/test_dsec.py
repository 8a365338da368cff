"""DSEC-style event HDF5: round trips, the millisecond index, any integer widths, missing filters."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest

from psfmt.errors import FormatError
from psfmt.eventfiles import dsec
from psfmt.eventfiles.structured import TONIC_DTYPE, from_structured, to_tonic
from psfmt.events import EventArray


def sample(n: int = 4000, seed: int = 0) -> EventArray:
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, 5_000_000, n)) + 1_234_567
    return EventArray(rng.integers(0, 64, n), rng.integers(0, 48, n), t, rng.choice([-1, 1], n))


def same(a: EventArray, b: EventArray) -> bool:
    return len(a) == len(b) and all(np.array_equal(getattr(a, c), getattr(b, c)) for c in "xytp")


@pytest.mark.parametrize("compression", ["gzip", "zstd", "none"])
def test_round_trip_and_index(tmp_path: Path, compression: str) -> None:
    if compression == "zstd":
        pytest.importorskip("hdf5plugin")
    events = sample()
    path = tmp_path / f"{compression}.h5"
    dsec.write_dsec(path, events.chunks(333), len(events), 64, 48, compression=compression)
    with h5py.File(path) as f:
        assert int(f["t_offset"][()]) == int(events.t[0])
        assert (f["events/x"].dtype, f["events/p"].dtype, f["events/t"].dtype) == (np.uint16, np.uint8, np.uint32)
        t_rel = f["events/t"][:].astype(np.int64)
        index = f["ms_to_idx"][:]
    assert np.array_equal(index, np.searchsorted(t_rel, 1000 * np.arange(t_rel[-1] // 1000 + 1), side="left"))
    with dsec.DsecFile(path) as f:
        assert (f.width, f.height, f.count) == (64, 48, len(events))
        assert same(f.read(), events)
        assert same(EventArray.concatenate(list(f.chunks(500))), events)
        for t0, t1 in [(0, 10**8), (1_300_000, 1_300_001), (2_000_500, 4_100_250), (9 * 10**6, 10**7)]:
            assert same(f.window(t0, t1), events.window(t0, t1))


def test_any_integer_widths_are_read(tmp_path: Path) -> None:
    path = tmp_path / "wide.h5"
    with h5py.File(path, "w") as f:
        f["events/x"] = np.array([1, 2, 3], np.int32)
        f["events/y"] = np.array([4, 5, 6], np.int64)
        f["events/p"] = np.array([-1, 1, 0], np.int8)
        f["events/t"] = np.array([0, 7, 7], np.uint64)
        f["t_offset"] = np.int64(100)
    with dsec.DsecFile(path) as d:
        events = d.read()
        assert (d.width, d.height) == (None, None)
    assert events.x.tolist() == [1, 2, 3] and events.y.tolist() == [4, 5, 6]
    assert events.t.tolist() == [100, 107, 107] and events.p.tolist() == [-1, 1, -1]


def test_bad_files_are_one_line_errors(tmp_path: Path) -> None:
    path = tmp_path / "bad.h5"
    with h5py.File(path, "w") as f:
        f["events/x"] = np.zeros(3, np.uint16)
    with pytest.raises(FormatError, match=r"bad.h5: /events lacks y, p, t$"):
        dsec.DsecFile(path)
    with h5py.File(path, "a") as f:
        for c in "yp":
            f[f"events/{c}"] = np.zeros(3, np.uint16)
        f["events/t"] = np.zeros(3, np.float32)
    with pytest.raises(FormatError, match=r"/events/t is float32 of shape \(3,\), expected 1-D integers"):
        dsec.DsecFile(path)
    with pytest.raises(FormatError, match="not a DSEC-style event file"):
        h5py.File(tmp_path / "empty.h5", "w").close()
        dsec.DsecFile(tmp_path / "empty.h5")


def test_a_filter_that_is_not_installed_is_named(tmp_path: Path) -> None:
    hdf5plugin = pytest.importorskip("hdf5plugin")
    path = tmp_path / "zstd.h5"
    dsec.write_dsec(path, [sample(100)], 100, 64, 48, compression="zstd")
    h5py.h5z.unregister_filter(hdf5plugin.ZSTD_ID)
    try:
        with pytest.raises(FormatError, match=r"/events/x needs the HDF5 filter .*\(id 32015\), which is not installed \(pip install hdf5plugin\)"):
            dsec.DsecFile(path)
    finally:
        hdf5plugin.register("zstd", force=True)
    with dsec.DsecFile(path) as d:
        assert len(d.read()) == 100


def test_tonic_arrays() -> None:
    events = sample(50)
    arr = to_tonic(events)
    assert arr.dtype == TONIC_DTYPE and arr["p"].tolist() == (events.p > 0).tolist()
    assert same(from_structured(arr), events) and same(from_structured(events.to_structured()), events)
    with pytest.raises(ValueError, match=r"lack field\(s\) p"):
        from_structured(np.zeros(2, dtype=[("x", "i2"), ("y", "i2"), ("t", "i8")]))
