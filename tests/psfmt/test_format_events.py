"""Event storage: window reads through the millisecond index, streaming appends, chunk iteration."""

from __future__ import annotations

import tempfile
from pathlib import Path

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import psfmt
from psfmt.deflate import deflate_chunk
from psfmt.events import EVENT_DTYPES, MsIndexBuilder
from psfmt.writer import GROW_CHUNKS

SENSOR = 16


@st.composite
def event_streams(draw: st.DrawFn) -> psfmt.EventArray:
    """Sorted streams with repeated times, gaps of several ms, negative times and empty streams."""
    n = draw(st.integers(0, 120))
    start = draw(st.integers(-5_000, 5_000))
    steps = draw(st.lists(st.sampled_from([0, 0, 1, 7, 250, 999, 1000, 1001, 3500]), min_size=n, max_size=n))
    t = start + np.cumsum(np.asarray(steps, dtype=np.int64))
    rng = np.random.default_rng(draw(st.integers(0, 2**16)))
    return psfmt.EventArray(rng.integers(0, SENSOR, n), rng.integers(0, SENSOR, n), t, rng.choice([-1, 1], n))


def write_stream(path: Path, events: psfmt.EventArray, blocks: list[int] | None = None, chunk: int = 8) -> None:
    """Write with the streaming writer, appending in blocks of the given sizes (one block if None)."""
    with psfmt.CaptureWriter(path, created="2025-01-01T00:00:00+00:00", event_chunk=chunk) as writer:
        writer.begin_events(SENSOR, SENSOR)
        cuts = np.cumsum(blocks or [len(events)])
        for lo, hi in zip(np.concatenate([[0], cuts[:-1]]), cuts):
            writer.append_events(events[int(lo) : int(hi)])


def brute_force(events: psfmt.EventArray, t0: int, t1: int) -> np.ndarray:
    return np.flatnonzero((events.t >= t0) & (events.t < t1))


def assert_same_events(got: psfmt.EventArray, events: psfmt.EventArray, idx: np.ndarray) -> None:
    for c in "xytp":
        np.testing.assert_array_equal(getattr(got, c), getattr(events, c)[idx])


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(events=event_streams(), data=st.data())
def test_window_reads_equal_a_brute_force_filter(events: psfmt.EventArray, data: st.DataObject) -> None:
    lo = int(events.t[0]) if len(events) else 0
    hi = int(events.t[-1]) if len(events) else 0
    edge = st.integers(lo - 3_000, hi + 3_000)
    windows = data.draw(st.lists(st.tuples(edge, edge), min_size=1, max_size=8))
    windows += [(lo - 5_000, lo - 1), (hi + 1, hi + 4_000), (lo - 1, hi + 1), (lo, lo + 1000), (hi, hi)]
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "e.h5"
        write_stream(path, events)
        with psfmt.read(path) as capture:
            for t0, t1 in windows:
                if t1 < t0:  # a window given backwards is an error, not an empty read (issue 24)
                    for stream in (capture.events, events):
                        with pytest.raises(ValueError, match=r"ends before it starts"):
                            stream.window(t0, t1)
                    continue
                expected = brute_force(events, t0, t1)
                assert_same_events(capture.events.window(t0, t1), events, expected)
                assert_same_events(events.window(t0, t1), events, expected)


@settings(max_examples=40, deadline=None)
@given(events=event_streams(), seed=st.integers(0, 1000))
def test_many_small_appends_give_the_same_content_and_index_as_one(events: psfmt.EventArray, seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = len(events)
    cuts = np.sort(rng.integers(0, n + 1, size=int(rng.integers(0, n + 3))))
    blocks = [int(b) for b in np.diff(np.concatenate([[0], cuts, [n]]))]
    with tempfile.TemporaryDirectory() as folder:
        one, many = Path(folder) / "one.h5", Path(folder) / "many.h5"
        write_stream(one, events)
        write_stream(many, events, blocks)
        with h5py.File(one, "r") as a, h5py.File(many, "r") as b:
            for name in ("x", "y", "t", "p", "ms_to_idx"):
                np.testing.assert_array_equal(b["events"][name][()], a["events"][name][()])
            assert dict(b["events"].attrs) == dict(a["events"].attrs)
            origin = int(a["events"].attrs["ms_origin_us"])
            index = a["events/ms_to_idx"][()]
            np.testing.assert_array_equal(index, np.searchsorted(events.t, origin + 1000 * np.arange(len(index))))
            if len(events):
                assert origin == (int(events.t[0]) // 1000) * 1000
                assert origin + 1000 * (len(index) - 1) > events.t[-1] >= origin + 1000 * (len(index) - 2)
        assert psfmt.validate(many).errors == []


def test_columns_grow_ahead_and_end_exactly_as_long_as_the_events(tmp_path: Path) -> None:
    """Appends of 13 events into chunks of 8, far past the writer's first growth: the columns end
    exactly as long as the events, and every chunk, the partial last one too, is stored as the
    writer compressed it (the final resize cut none)."""
    rng = np.random.default_rng(4)
    n = 8 * (4 * GROW_CHUNKS) + 5
    events = psfmt.EventArray(rng.integers(0, SENSOR, n), rng.integers(0, SENSOR, n),
                              np.sort(rng.integers(0, 50_000, n)), rng.choice([-1, 1], n))
    write_stream(tmp_path / "e.h5", events, [13] * (n // 13) + [n % 13])
    chunks = -(-n // 8)
    with h5py.File(tmp_path / "e.h5", "r") as f:
        for c in "xytp":
            column, expected = f["events"][c], getattr(events, c).astype(EVENT_DTYPES[c])
            assert column.shape == (n,)
            np.testing.assert_array_equal(column[()], expected)
            assert column.id.get_num_chunks() == chunks
            for i in range(chunks):
                stored = column.id.read_direct_chunk((8 * i,))[1]
                assert stored == deflate_chunk(expected[8 * i : 8 * i + 8], (8,), 1)


@pytest.mark.parametrize("size", [None, 1, 7, 64, 10_000])
def test_chunk_iteration_covers_every_event_once_in_order(tmp_path: Path, size: int | None) -> None:
    rng = np.random.default_rng(1)
    n = 1_000
    events = psfmt.EventArray(rng.integers(0, SENSOR, n), rng.integers(0, SENSOR, n),
                              np.sort(rng.integers(0, 50_000, n)), rng.choice([-1, 1], n))
    write_stream(tmp_path / "e.h5", events, chunk=64)
    with psfmt.read(tmp_path / "e.h5") as capture:
        blocks = list(capture.events.chunks(size))
    assert all(len(b) == (size or len(b)) for b in blocks[:-1]) and len(blocks[-1]) <= (size or n)
    assert sum(len(b) for b in blocks) == n
    assert_same_events(psfmt.EventArray.concatenate(blocks), events, np.arange(n))
    in_memory = list(events.chunks(size or 300))
    assert [len(b) for b in in_memory] == ([300, 300, 300, 100] if size is None else [len(b) for b in blocks])


def test_empty_stream_has_a_one_entry_index_and_empty_windows(tmp_path: Path) -> None:
    write_stream(tmp_path / "e.h5", psfmt.EventArray.empty())
    with h5py.File(tmp_path / "e.h5", "r") as f:
        np.testing.assert_array_equal(f["events/ms_to_idx"][()], [0])
        assert f["events"].attrs["ms_origin_us"] == 0
    with psfmt.read(tmp_path / "e.h5") as capture:
        assert len(capture.events) == 0 and capture.events.t_first_us is None
        assert len(capture.events.window(-10**9, 10**9)) == 0
        assert list(capture.events.chunks()) == []
        assert len(capture.events.read()) == 0
    assert psfmt.validate(tmp_path / "e.h5").errors == []


def test_a_window_reads_only_the_chunks_it_needs(tmp_path: Path) -> None:
    # every storage chunk but the one holding the window is corrupted: the window read must not touch them
    n, chunk = 200_000, 1000
    events = psfmt.EventArray(np.zeros(n), np.zeros(n), np.arange(n, dtype=np.int64) * 5, np.ones(n))
    path = tmp_path / "e.h5"
    write_stream(path, events, chunk=chunk)
    keep = 100
    # the first and last chunks of t stay readable: opening a capture reads the first and last times
    intact = {0, keep, n // chunk - 1}
    with h5py.File(path, "r") as f:
        spans = [
            (info.byte_offset, info.size)
            for c in "xytp"
            for i in range(n // chunk)
            if i not in intact
            for info in [f["events"][c].id.get_chunk_info(i)]
        ]
    raw = bytearray(path.read_bytes())
    for offset, size in spans:
        raw[offset : offset + size] = bytes(size)
    path.write_bytes(bytes(raw))
    with psfmt.read(path) as capture:
        window = capture.events.window(keep * chunk * 5, keep * chunk * 5 + 1000)
        np.testing.assert_array_equal(window.t, np.arange(keep * chunk * 5, keep * chunk * 5 + 1000, 5))
        with pytest.raises(psfmt.FormatError, match=r"e\.h5: damaged HDF5 file \(filter returned failure during read\)$"):
            capture.events.read()


def test_index_builder_matches_searchsorted_for_any_split() -> None:
    t = np.array([-2500, -2500, -1000, -1, 0, 0, 999, 1000, 1001, 7_000, 7_999], dtype=np.int64)
    origin = -3000
    expected = np.searchsorted(t, origin + 1000 * np.arange(12), side="left")
    for cuts in ([], [1], [2, 5], [3, 4, 8, 10], list(range(1, len(t)))):
        builder = MsIndexBuilder()
        for part in np.split(t, cuts):
            builder.add(part)
        assert builder.origin_us == origin
        np.testing.assert_array_equal(builder.finish(), expected)


def test_appends_out_of_order_are_refused(tmp_path: Path) -> None:
    events = psfmt.EventArray([0, 1], [0, 1], [100, 200], [1, -1])
    with pytest.raises(psfmt.FormatError, match=r"appended events start at 150 µs, before the last written 200 µs$"):
        with psfmt.CaptureWriter(tmp_path / "e.h5") as writer:
            writer.begin_events(SENSOR, SENSOR)
            writer.append_events(events)
            writer.append_events(psfmt.EventArray([0], [0], [150], [1]))
    with pytest.raises(psfmt.FormatError, match=r"appended events are not sorted by time$"):
        with psfmt.CaptureWriter(tmp_path / "e.h5") as writer:
            writer.begin_events(SENSOR, SENSOR)
            writer.append_events(events[::-1])
    with pytest.raises(psfmt.FormatError, match=r"begin_events\(width, height\) must come before append_events$"):
        with psfmt.CaptureWriter(tmp_path / "e.h5") as writer:
            writer.append_events(events)
    assert list(tmp_path.iterdir()) == []
