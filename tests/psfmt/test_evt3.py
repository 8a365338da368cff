"""EVT 3.0: the vendor's decoding rules word by word, bit-exact round trips, streaming, windows, fuzzing."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import psfmt
from psfmt.errors import FormatError
from psfmt.eventfiles import evt3
from psfmt.eventfiles._evt3 import decoding, encoding
from psfmt.eventfiles._evt3.engine import has_numba
from psfmt.eventfiles.rawheader import format_header, read_header
from psfmt.events import EventArray

ENGINES = ["numpy"] + (["numba"] if has_numba() else [])


def th(h: int) -> int:
    return 0x8000 | h


def tl(low: int) -> int:
    return 0x6000 | low


def ay(y: int) -> int:
    return y


def ax(x: int, p: int = 1) -> int:
    return 0x2000 | (p << 11) | x


def words(*ws: int) -> bytes:
    return np.asarray(ws, dtype="<u2").tobytes()


def reference(data: bytes, width: int = 2048, height: int = 2048) -> tuple[EventArray, psfmt.Triggers, np.ndarray]:
    """The decoding loop run by the interpreter: the reference both engines must match."""
    w = np.frombuffer(data, "<u2")
    state = np.array(decoding.DECODER_STATE, np.int64)
    counters = np.zeros(6, np.int64)
    cap = 12 * len(w) + 12
    out = [np.empty(cap, np.uint16), np.empty(cap, np.uint16), np.empty(cap, np.int64), np.empty(cap, np.int8)]
    trig = [np.empty(len(w) + 1, np.int64), np.empty(len(w) + 1, np.uint8), np.empty(len(w) + 1, np.int8)]
    n, m, used = decoding.decode_loop(w, state, counters, width, height, *out, *trig)
    assert used == len(w)
    return EventArray(*(a[:n] for a in out)), psfmt.Triggers(*(a[:m] for a in trig)), counters


def same(a: EventArray, b: EventArray) -> bool:
    return len(a) == len(b) and all(np.array_equal(getattr(a, c), getattr(b, c)) for c in "xytp")


@pytest.mark.parametrize("engine", ENGINES)
def test_time_rules_of_the_vendor_decoder(engine: str) -> None:
    data = words(
        th(5), tl(100), ay(3), ax(10),  # t = 5·4096 + 100
        th(5), ax(11),  # the same TIME_HIGH again keeps the low bits
        tl(90), ax(12),  # a small backward TIME_LOW step is taken as it is, not as a wrap
        th(6), ax(13),  # a changed TIME_HIGH resets the low bits
        th(4), ax(14),  # 2 below: a step back, not a wrap
        th(4000), th(1), tl(7), ax(15),  # 3999 below: a wrap
    )
    events, _, stats = evt3.decode(data, engine=engine)
    base = 1 << 24
    assert events.t.tolist() == [5 * 4096 + 100, 5 * 4096 + 100, 5 * 4096 + 90, 6 * 4096, 4 * 4096, base + 4096 + 7]
    assert events.x.tolist() == [10, 11, 12, 13, 14, 15] and set(events.y.tolist()) == {3}
    assert stats.clean


@pytest.mark.parametrize("engine", ENGINES)
def test_vectors_advance_their_base_and_keep_its_polarity(engine: str) -> None:
    data = words(th(0), tl(1), ay(9), 0x3000 | 100, 0x4000 | 0b101, 0x4000 | (1 << 11), 0x5000 | 0x81, 0x3800 | 7, 0x5000 | 1)
    events, _, stats = evt3.decode(data, engine=engine)
    assert events.x.tolist() == [100, 102, 100 + 12 + 11, 100 + 24, 100 + 24 + 7, 7]
    assert events.p.tolist() == [-1, -1, -1, -1, -1, 1]
    assert stats.events == 6 and stats.clean


@pytest.mark.parametrize("engine", ENGINES)
def test_words_without_meaning_are_skipped_and_counted(engine: str) -> None:
    data = words(
        ax(1),  # before any TIME_HIGH
        th(0), ax(2),  # before any ADDR_Y
        0x4000 | 3,  # a vector without a VECT_BASE_X
        0xE123, 0xF000, 0x7001,  # OTHERS, CONTINUED_12, CONTINUED_4
        0x1000, 0x9000, 0xB000, 0xC000, 0xD000,  # undefined word types
        ay(5000 & 0x7FF), ax(3),  # y = 904 outside a 640×480 sensor
        ay(1), ax(700), ax(4),  # x outside, then one good event
        0xA000 | (3 << 8) | 1,  # trigger: channel 3, rising edge
    )
    events, triggers, stats = evt3.decode(data, 640, 480, engine=engine)
    assert events.x.tolist() == [4] and events.y.tolist() == [1]
    assert (triggers.t.tolist(), triggers.channel.tolist(), triggers.value.tolist()) == ([0], [3], [1])
    assert (stats.no_time, stats.no_y, stats.no_base, stats.others, stats.unknown, stats.outside) == (1, 1, 1, 3, 5, 2)
    assert stats.summary() == (
        "1 events, 1 triggers from 18 words; 3 OTHERS/CONTINUED words skipped; 5 words of unknown type skipped; "
        "1 words before the first TIME_HIGH skipped; 1 event words before the first ADDR_Y skipped; "
        "1 vector words without VECT_BASE_X skipped; 2 events outside the sensor geometry dropped"
    )


sorted_streams = st.integers(1, 250).flatmap(
    lambda n: st.tuples(
        st.lists(st.integers(0, 2047), min_size=n, max_size=n),
        st.lists(st.integers(0, 2047), min_size=n, max_size=n),
        st.lists(st.integers(0, 3 * (1 << 24)), min_size=n, max_size=n),
        st.lists(st.booleans(), min_size=n, max_size=n),
        st.integers(0, 1 << 40),
        st.booleans(),
    )
)


def _stream(data: tuple) -> EventArray:
    x, y, t, p, offset, rows = data
    x, y, t = np.asarray(x), np.asarray(y), np.sort(np.asarray(t, np.int64)) + offset
    if rows:  # dense rows: runs of one time and row with rising x, the case the vectors are for
        y, t = y % 3, t // 50000 * 50000
        order = np.lexsort((x, y, t))
        x, y, t = x[order], y[order], t[order]
    return EventArray(x, y, t, np.where(p, 1, -1))


@settings(max_examples=40, deadline=None)
@given(sorted_streams)
def test_round_trip_is_bit_exact_and_engines_agree(data: tuple) -> None:
    events = _stream(data)
    encoded = evt3.encode(events, engine="numpy")
    state = np.array(encoding.ENCODER_STATE, np.int64)
    out = np.empty(4 * len(events) + 2 * (int(events.t[-1]) >> 24) + 8, np.uint16)
    k = encoding.encode_loop(events.x, events.y, events.t, events.p, out, state)
    assert out[:k].astype("<u2").tobytes() == encoded
    for engine in ENGINES:
        assert evt3.encode(events, engine=engine) == encoded
        decoded, _, stats = evt3.decode(encoded, engine=engine)
        assert same(decoded, events) and stats.clean


def test_vectors_are_written_as_triplets_and_pay_off() -> None:
    x = np.arange(0, 64, dtype=np.uint16)
    events = EventArray(x, np.full(64, 7), np.full(64, 1 << 30), np.ones(64))
    w = np.frombuffer(evt3.encode(events), "<u2")
    types = (w >> 12).tolist()
    # TIME_HIGH steps through 64 wraps (0xFFF, 0 each), then the time, the row and two base+triplets
    assert types[-9:] == [0x0, 0x3, 0x4, 0x4, 0x5, 0x3, 0x4, 0x4, 0x5]
    assert len(w) == 1 + 2 * 64 + 1 + 8  # first TIME_HIGH, 64 wraps (the first from 0 needs 2), ADDR_Y, 2 × 4
    assert same(evt3.decode(w)[0], events)


def test_chunk_boundaries_change_neither_bytes_nor_events(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    n = 2000
    t = np.sort(rng.integers(0, 1 << 26, n))
    events = EventArray(rng.integers(0, 64, n), rng.integers(0, 32, n), t, rng.choice([-1, 1], n))
    path = tmp_path / "rec.raw"
    evt3.write_raw(path, events.chunks(97), 64, 32, header={"camera_integrator_name": "Prophesee"})
    assert path.read_bytes().endswith(evt3.encode(events))
    header = read_header(path)
    assert (header.width, header.height, header.encoding) == (64, 32, "EVT3")
    assert header.fields["camera_integrator_name"] == "Prophesee"
    for engine in ENGINES:
        whole = evt3.Evt3File(path, engine=engine).read()[0]
        small = evt3.Evt3File(path, engine=engine, chunk_words=7)
        parts = EventArray.concatenate([e for e, _ in small.chunks()])
        assert same(whole, events) and same(parts, events) and small.stats.events == n
        t0, t1 = int(t[500]), int(t[1400]) + 1
        window = evt3.Evt3File(path, engine=engine, chunk_words=64).window(t0, t1)
        assert same(window, events.window(t0, t1))


def test_damaged_files_are_reported_not_crashed_on(tmp_path: Path) -> None:
    events = EventArray(np.arange(10), np.zeros(10), np.arange(10) * 5, np.ones(10))
    path = tmp_path / "cut.raw"
    evt3.write_raw(path, [events], 16, 16)
    data = path.read_bytes()
    path.write_bytes(data[:-1])
    reader = evt3.Evt3File(path)
    decoded, _ = reader.read()
    assert len(decoded) == 9 and reader.stats.trailing_bytes == 1
    assert reader.stats.trailing_offset == len(data) - 2
    assert f"1 trailing byte(s) of a cut-off word at byte {len(data) - 2} ignored" in reader.stats.summary()
    header_only = tmp_path / "empty.raw"
    header_only.write_bytes(data[: read_header(path).data_offset])
    assert len(evt3.Evt3File(header_only).read()[0]) == 0
    garbage = tmp_path / "garbage.raw"
    garbage.write_bytes(bytes(range(256)) * 4)
    with pytest.raises(FormatError, match=r"garbage.raw: RAW header declares no sensor geometry"):
        evt3.Evt3File(garbage)
    with pytest.raises(ValueError, match="sorted by time"):
        evt3.encode(EventArray(np.zeros(2), np.zeros(2), np.array([5, 4]), np.ones(2)))
    with pytest.raises(ValueError, match="11-bit"):
        evt3.encode(EventArray(np.array([2048]), np.zeros(1), np.zeros(1), np.ones(1)))


@settings(max_examples=150, deadline=None)
@given(st.lists(st.integers(0, 0xFFFF), max_size=300), st.integers(1, 2048), st.integers(1, 2048))
def test_fuzzed_word_streams_decode_alike_and_within_bounds(ws: list[int], width: int, height: int) -> None:
    data = np.asarray(ws, dtype="<u2").tobytes()
    ref_events, ref_triggers, counters = reference(data, width, height)
    for engine in ENGINES:
        events, triggers, stats = evt3.decode(data, width, height, engine=engine)
        assert same(events, ref_events)
        assert np.array_equal(triggers.t, ref_triggers.t) and np.array_equal(triggers.channel, ref_triggers.channel)
        assert [getattr(stats, k) for k in stats.COUNTERS] == counters.tolist()
        assert (events.x < width).all() and (events.y < height).all()
        # split anywhere, the streaming decoder gives the same
        decoder = evt3.Decoder(width, height, engine)
        cut = len(ws) // 3
        parts = [decoder.feed(np.asarray(ws[:cut], np.uint16))[0], decoder.feed(np.asarray(ws[cut:], np.uint16))[0]]
        assert same(EventArray.concatenate(parts), ref_events)


def test_the_vendor_compatible_decoder_reads_our_files(tmp_path: Path) -> None:
    vendor = pytest.importorskip("evt3", reason="the evt3 package (extra 'bench') is not installed")
    rng = np.random.default_rng(5)
    n = 3000
    t = np.sort(rng.integers(0, 3 << 24, n))
    x, y = rng.integers(0, 64, n), rng.integers(0, 4, n)
    order = np.lexsort((x, y, t // 1000))
    events = EventArray(x[order], y[order], t // 1000 * 1000, rng.choice([-1, 1], n))
    path = tmp_path / "v.raw"
    evt3.write_raw(path, [events], 64, 48)
    theirs = vendor.decode_file(str(path))
    assert np.array_equal(np.asarray(theirs.t, np.int64), events.t)
    assert np.array_equal(np.asarray(theirs.x), events.x) and np.array_equal(np.asarray(theirs.y), events.y)
    assert np.array_equal(np.where(np.asarray(theirs.p) > 0, 1, -1), events.p)


def test_whole_file_read_grows_its_output_past_a_word_per_event(tmp_path: Path) -> None:
    """Full vectors give 12 events a word, so reading a file whole grows its one output (and
    triggers past the first thousand) several times; both engines and the reference agree."""
    vec = [0x3000 | 5, 0x4FFF, 0x4FFF, 0x50FF] * 300
    body = [th(1), tl(3), ay(2), *vec, *[0xA000 | (k & 1) for k in range(2500)], ax(7)]
    path = tmp_path / "dense.raw"
    path.write_bytes(format_header("EVT3", 2048, 4) + words(*body))
    ref_events, ref_triggers, _ = reference(words(*body))
    assert len(ref_events) == 300 * 32 + 1 and len(ref_triggers) == 2500
    for engine in ENGINES:
        raw = evt3.Evt3File(path, engine=engine, chunk_words=100)
        events, triggers = raw.read()
        assert same(events, ref_events) and np.array_equal(triggers.value, ref_triggers.value)
        assert raw.stats.events == len(ref_events) and raw.stats.triggers == 2500


@pytest.mark.skipif(not has_numba(), reason="numba not installed")
def test_two_thread_read_matches_the_block_by_block_decode(tmp_path: Path) -> None:
    """A file past ``PARALLEL_MIN_WORDS`` (vectors, wraps of the 24-bit time, triggers-free) read whole
    on two threads gives the events and stats of decoding it block by block on one."""
    rng = np.random.default_rng(11)
    n = 300_000
    t = np.sort(rng.integers(0, 3 << 24, n))  # two wraps
    x = np.where(rng.random(n) < 0.5, np.arange(n) % 32 + 100, rng.integers(0, 640, n))
    events = EventArray(x, rng.integers(0, 480, n), t // 64 * 64, np.where(rng.random(n) < 0.5, 1, -1))
    order = np.lexsort((events.x, events.y, events.t))
    events = events[order]
    path = tmp_path / "big.raw"
    evt3.write_raw(path, [events], 640, 480)
    assert (path.stat().st_size - read_header(path).data_offset) // 2 >= evt3.PARALLEL_MIN_WORDS
    whole = evt3.Evt3File(path, engine="numba")
    got, _ = whole.read()
    blocks = evt3.Evt3File(path, engine="numba", chunk_words=1 << 16)
    want = EventArray.concatenate([e for e, _ in blocks.chunks()])
    assert same(got, want) and same(got, events)
    assert whole.stats.summary() == blocks.stats.summary()
