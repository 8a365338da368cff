"""EVT 2.0: decoding word by word, round trips through RAW files, damaged and fuzzed input."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from psfmt.eventfiles import evt2
from psfmt.eventfiles.rawheader import read_header
from psfmt.events import EventArray


def cd(x: int, y: int, t_low: int, on: bool) -> int:
    return ((1 if on else 0) << 28) | (t_low << 22) | (x << 11) | y


def words(*ws: int) -> bytes:
    return np.asarray(ws, dtype="<u4").tobytes()


def test_words_decode_to_events_and_triggers() -> None:
    data = words(
        cd(1, 1, 0, True),  # before any TIME_HIGH: skipped
        0x80000000 | 1000,  # time bits 33..6 = 1000
        cd(5, 6, 7, True),
        cd(2047, 3, 63, False),  # x outside a 640-wide sensor
        0xA0000000 | (9 << 22) | (17 << 8) | 1,  # trigger: channel 17, rising
        0xE0000000, 0x30000000,  # OTHERS skipped, an undefined type counted
        cd(8, 9, 1, False),
    )
    events, triggers, stats = evt2.decode(data, 640, 480)
    assert events.x.tolist() == [5, 8] and events.y.tolist() == [6, 9] and events.p.tolist() == [1, -1]
    assert events.t.tolist() == [1000 * 64 + 7, 1000 * 64 + 1]
    assert (triggers.t.tolist(), triggers.channel.tolist(), triggers.value.tolist()) == ([64009], [17], [1])
    assert (stats.no_time, stats.outside, stats.others, stats.unknown) == (1, 1, 1, 1)


@settings(max_examples=30, deadline=None)
@given(
    st.integers(1, 120).flatmap(
        lambda n: st.tuples(
            st.lists(st.integers(0, 2047), min_size=n, max_size=n),
            st.lists(st.integers(0, 2047), min_size=n, max_size=n),
            st.lists(st.integers(0, (1 << 34) - 1), min_size=n, max_size=n),
            st.lists(st.booleans(), min_size=n, max_size=n),
        )
    )
)
def test_round_trip_is_exact(data: tuple) -> None:
    x, y, t, p = data
    events = EventArray(x, y, np.sort(np.asarray(t, np.int64)), np.where(p, 1, -1))
    encoded, _ = evt2.encode(events)
    decoded, _, stats = evt2.decode(encoded)
    assert all(np.array_equal(getattr(decoded, c), getattr(events, c)) for c in "xytp") and stats.clean


def test_raw_file_streams_in_blocks(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    n = 3000
    events = EventArray(rng.integers(0, 40, n), rng.integers(0, 30, n), np.sort(rng.integers(0, 10**7, n)), rng.choice([-1, 1], n))
    path = tmp_path / "rec.raw"
    evt2.write_raw(path, events.chunks(101), 40, 30)
    assert read_header(path).encoding == "EVT2"
    reader = evt2.Evt2File(path, chunk_words=13)
    decoded, triggers = reader.read()
    assert all(np.array_equal(getattr(decoded, c), getattr(events, c)) for c in "xytp")
    assert len(triggers) == 0 and reader.stats.events == n and reader.stats.clean
    path.write_bytes(path.read_bytes()[:-3])
    cut = evt2.Evt2File(path)
    assert len(cut.read()[0]) == n - 1 and cut.stats.trailing_bytes == 1


@settings(max_examples=100, deadline=None)
@given(st.lists(st.integers(0, 0xFFFFFFFF), max_size=200))
def test_fuzzed_words_never_crash_and_stay_in_bounds(ws: list[int]) -> None:
    events, _, stats = evt2.decode(words(*ws), 320, 240)
    assert (events.x < 320).all() and (events.y < 240).all() and (events.t >= 0).all()
    assert stats.events + stats.triggers + stats.others + stats.unknown + stats.no_time + stats.outside <= len(ws)
    with pytest.raises(ValueError, match="sorted"):
        evt2.encode(EventArray(np.zeros(2), np.zeros(2), np.array([3, 1]), np.ones(2)))
