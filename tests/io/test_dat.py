"""Issue 25: Metavision DAT files of CD events: the record layout, exact round trips, damaged files
(which get the answers a damaged RAW file gets), and ``convert dat`` / ``convert raw FILE.dat``."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import psfmt
from psfmt.errors import FormatError
from psfmt.eventfiles import dat, evt3
from psfmt.eventfiles.rawheader import DecodeStats, format_header
from psfmt.events import EventArray
from pstoolkit.cli import main


def record(t: int, x: int, y: int, p: int) -> bytes:
    """One record packed by hand as OpenEB's Event2d::RawEvent lays it out: uint32 ts, then x in
    bits 0–13, y in bits 14–27, p in bits 28–31 of a little-endian uint32."""
    return int(t).to_bytes(4, "little") + (x | (y << 14) | (p << 28)).to_bytes(4, "little")


def dat_file(path: Path, records: bytes, header: bytes | None = None) -> Path:
    path.write_bytes((header if header is not None else b"% Data file containing CD events\n% Version 2\n% Width 16\n% Height 12\n")
                     + bytes([12, 8]) + records)
    return path


def same(a: EventArray, b: EventArray) -> bool:
    return len(a) == len(b) and all(np.array_equal(getattr(a, c), getattr(b, c)) for c in "xytp")


def test_the_record_layout_is_openeb_s() -> None:
    data = record(123, 5, 7, 1) + record(4_000_000_000, 16383, 16383, 0)
    events = dat.decode(data)
    assert events.x.tolist() == [5, 16383] and events.y.tolist() == [7, 16383]
    assert events.t.tolist() == [123, 4_000_000_000] and events.p.tolist() == [1, -1]
    assert dat.encode(events) == data
    assert dat.format_header(640, 480) == b"% Data file containing CD events\n% Version 2\n% Width 640\n% Height 480\n\x0c\x08"


@settings(max_examples=60, deadline=None)
@given(
    st.integers(0, 200).flatmap(
        lambda n: st.tuples(
            st.lists(st.integers(0, 16383), min_size=n, max_size=n),
            st.lists(st.integers(0, 16383), min_size=n, max_size=n),
            st.lists(st.integers(0, (1 << 32) - 1), min_size=n, max_size=n),
            st.lists(st.booleans(), min_size=n, max_size=n),
        )
    )
)
def test_round_trip_is_exact(data: tuple) -> None:
    x, y, t, p = data
    events = EventArray(np.asarray(x, np.int64), np.asarray(y, np.int64), np.asarray(t, np.int64), np.where(p, 1, -1))
    stats = DecodeStats(unit="record")
    assert same(dat.decode(dat.encode(events), stats=stats), events) and stats.clean and stats.events == len(x)


def test_files_round_trip_in_blocks_and_refuse_what_the_format_cannot_hold(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    n = 3000
    events = EventArray(rng.integers(0, 1280, n), rng.integers(0, 720, n), np.sort(rng.integers(0, 1 << 32, n)), rng.choice([-1, 1], n))
    path = dat.write_dat(tmp_path / "rec.dat", events.chunks(101), 1280, 720, header={"Date": "2024-01-02 03:04:05"})
    reader = dat.DatFile(path, chunk_records=97)
    assert (reader.width, reader.height, reader.event_type) == (1280, 720, 12)
    assert reader.header.geometry_source == "Width 1280, Height 720" and "% Date 2024-01-02 03:04:05" in reader.header.lines
    assert same(EventArray.concatenate(list(reader.chunks())), events) and reader.stats.clean
    assert reader.stats.summary() == f"{n:,} events, 0 triggers from {n:,} records"
    with pytest.raises(ValueError, match="uint32"):
        dat.encode(EventArray(np.zeros(1), np.zeros(1), np.array([-1]), np.ones(1)))
    with pytest.raises(ValueError, match="uint32"):
        dat.encode(EventArray(np.zeros(1), np.zeros(1), np.array([1 << 32]), np.ones(1)))
    with pytest.raises(ValueError, match="14-bit"):
        dat.encode(EventArray(np.array([16384]), np.zeros(1), np.zeros(1), np.ones(1)))
    with pytest.raises(FormatError, match="up to 16384"):
        dat.write_dat(tmp_path / "big.dat", [], 20000, 10)


def test_damaged_dat_files_are_reported_not_crashed_on(tmp_path: Path) -> None:
    good = record(10, 1, 2, 1) + record(20, 3, 4, 0)
    cut = dat.DatFile(dat_file(tmp_path / "cut.dat", good + record(30, 5, 6, 1)[:5]))
    assert len(cut.read()) == 2 and (cut.stats.trailing_bytes, cut.stats.trailing_offset) == (5, cut.data_offset + 16)
    assert cut.stats.summary().endswith(f"5 trailing byte(s) of a cut-off record at byte {cut.data_offset + 16} ignored")
    odd = dat.DatFile(dat_file(tmp_path / "odd.dat", good + record(30, 40, 6, 1) + record(40, 5, 6, 3)))
    assert len(odd.read()) == 2 and (odd.stats.outside, odd.stats.bad_polarity) == (1, 1) and not odd.stats.clean
    assert odd.stats.summary() == (
        "2 events, 0 triggers from 4 records; 1 events outside the sensor geometry dropped; "
        "1 records with a polarity other than 0 or 1 skipped"
    )
    header = b"% Width 16\n% Height 12\n"
    only = tmp_path / "header_only.dat"
    only.write_bytes(header)
    assert len(dat.DatFile(only).read()) == 0
    half = tmp_path / "half_pair.dat"
    half.write_bytes(header + b"\x0c")
    reader = dat.DatFile(half)
    assert len(reader.read()) == 0 and reader.stats.trailing_bytes == 1
    refusals = {
        "bare.dat": (good, "no '% ' header lines: not a Metavision DAT file"),
        "trigger.dat": (header + bytes([14, 8]) + good, "DAT file holds external-trigger events (type 14), not CD events"),
        "type.dat": (header + bytes([99, 8]) + good, "DAT event type 99 is not CD (12) or Event2d (0): not a DAT file of CD events"),
        "size.dat": (header + bytes([12, 16]) + good, "DAT events are 16 bytes, not 8"),
        "nosize.dat": (b"% Version 2\n" + bytes([12, 8]) + good, "DAT header declares no sensor geometry: no % geometry WxH"),
        "badsize.dat": (b"% Width 16\n% Height twelve\n" + bytes([12, 8]), "DAT header has an unreadable sensor geometry (% Width 16, % Height twelve)"),
    }
    for name, (content, message) in refusals.items():
        path = tmp_path / name
        path.write_bytes(content)
        with pytest.raises(FormatError) as err:
            dat.DatFile(path)
        assert str(err.value).startswith(f"{path}: {message}")
    assert len(dat.DatFile(tmp_path / "nosize.dat", geometry=(16, 12)).read()) == 2


def raw_file(path: Path, words: list[int]) -> Path:
    path.write_bytes(format_header("EVT3", 16, 12) + np.asarray(words, "<u2").tobytes())
    return path


# The same damage done to a RAW (EVT 3.0) file and to a DAT file; the two get the same answers.
DAMAGE = {
    # name: (RAW words, DAT records, what the warning line or the refusal says for RAW, for DAT)
    "clean": (
        [0x8000, 0x6000 | 10, 0x0002, 0x2800 | 1, 0x6000 | 20, 0x0004, 0x2000 | 3],
        record(10, 1, 2, 1) + record(20, 3, 4, 0),
        None, None,
    ),
    "outside": (
        [0x8000, 0x6000 | 10, 0x0002, 0x2800 | 1, 0x2800 | 40],
        record(10, 1, 2, 1) + record(10, 40, 2, 1),
        "1 events, 0 triggers from 5 words; 1 events outside the sensor geometry dropped",
        "1 events, 0 triggers from 2 records; 1 events outside the sensor geometry dropped",
    ),
    "backwards": (
        [0x8000, 0x6000 | 50, 0x0002, 0x2800 | 1, 0x6000 | 40, 0x2800 | 2],
        record(50, 1, 2, 1) + record(40, 2, 2, 1),
        "1 events stamped before their predecessor got its time",
        "1 events stamped before their predecessor got its time",
    ),
}


@pytest.mark.parametrize("kind", sorted(DAMAGE))
def test_a_damaged_dat_gets_the_answers_a_damaged_raw_gets(tmp_path: Path, caplog: pytest.LogCaptureFixture, kind: str) -> None:
    words, records, raw_note, dat_note = DAMAGE[kind]
    raw = raw_file(tmp_path / "rec.raw", words)
    dat_path = dat_file(tmp_path / "rec.dat", records)
    results = {}
    for src, note in ((raw, raw_note), (dat_path, dat_note)):
        out = tmp_path / f"{src.suffix[1:]}.h5"
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="pstoolkit.eventfiles"):
            assert main(["convert", "raw", str(src), "-o", str(out), "-q"]) == 0
        assert caplog.messages == ([f"{src}: {note}"] if note else [])
        with psfmt.read(out) as capture:
            results[src.suffix] = capture.events.read()
            assert (capture.events.width, capture.events.height) == (16, 12)
    assert same(results[".raw"], results[".dat"])


def test_truncated_and_refused_files_get_the_same_answers(tmp_path: Path, caplog: pytest.LogCaptureFixture, capsys: pytest.CaptureFixture[str]) -> None:
    raw = raw_file(tmp_path / "cut.raw", [0x8000, 0x6000 | 10, 0x0002, 0x2800 | 1, 0x2800 | 2])
    raw.write_bytes(raw.read_bytes()[:-1])
    cut_dat = dat_file(tmp_path / "cut.dat", record(10, 1, 2, 1) + record(10, 2, 2, 1))
    cut_dat.write_bytes(cut_dat.read_bytes()[:-3])
    raw_end = raw.stat().st_size - 1
    dat_end = cut_dat.stat().st_size - 5
    expected = {
        raw: f"1 events, 0 triggers from 4 words; 1 trailing byte(s) of a cut-off word at byte {raw_end} ignored",
        cut_dat: f"1 events, 0 triggers from 1 records; 5 trailing byte(s) of a cut-off record at byte {dat_end} ignored",
    }
    for src, note in expected.items():
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="pstoolkit.eventfiles"):
            assert main(["convert", "raw", str(src), "-o", str(tmp_path / f"{src.name}.h5"), "-q"]) == 0
        assert caplog.messages == [f"{src}: {note}"]

    refused = {
        # every event outside the sensor, a header alone: no events, refused unless --allow-empty
        raw_file(tmp_path / "outside.raw", [0x8000, 0x0050, 0x2800 | 40]): "no events to convert (0 events, 0 triggers from 3 words; "
        "1 events outside the sensor geometry dropped); --allow-empty writes the empty capture anyway",
        dat_file(tmp_path / "outside.dat", record(0, 40, 80, 1)): "no events to convert (0 events, 0 triggers from 1 records; "
        "1 events outside the sensor geometry dropped); --allow-empty writes the empty capture anyway",
        raw_file(tmp_path / "empty.raw", []): "no events to convert; --allow-empty writes the empty capture anyway",
        dat_file(tmp_path / "empty.dat", b""): "no events to convert; --allow-empty writes the empty capture anyway",
    }
    bare_raw, bare_dat = tmp_path / "bare.raw", tmp_path / "bare.dat"
    bare_raw.write_bytes(np.arange(8, dtype="<u2").tobytes())
    bare_dat.write_bytes(record(1, 2, 3, 1))
    refused[bare_raw] = "no '% evt' or '% format' header line: not a Prophesee RAW file"
    refused[bare_dat] = "no '% ' header lines: not a Metavision DAT file"
    for label, src in (("RAW", tmp_path / "nosize.raw"), ("DAT", tmp_path / "nosize.dat")):
        src.write_bytes(b"% evt 3.0\n" if label == "RAW" else b"% Version 2\n\x0c\x08")
        refused[src] = (
            f"{label} header declares no sensor geometry: no % geometry WxH, no width=/height= in % format, no % Width/% Height, "
            "and no Prophesee sensor known from system_ID, plugin_name, sensor_name or sensor_generation; "
            "give the sensor size with --geometry WxH"
        )
    for src, why in refused.items():
        out = tmp_path / f"{src.name}.h5"
        capsys.readouterr()
        assert main(["convert", "raw", str(src), "-o", str(out)]) == 2
        assert capsys.readouterr().err == f"pstoolkit: error: {src}: {why}\n"
        assert not out.exists()


def test_convert_dat_and_convert_raw_read_a_dat_exactly(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rng = np.random.default_rng(7)
    n = 2500
    events = EventArray(rng.integers(0, 640, n), rng.integers(0, 480, n), np.sort(rng.integers(0, 1 << 32, n)), rng.choice([-1, 1], n))
    src = dat.write_dat(tmp_path / "rec.dat", events.chunks(500), 640, 480, header={"Date": "2020-09-14 14:18:29"})
    renamed = tmp_path / "rec.bin"  # found by its header, whatever its name
    renamed.write_bytes(src.read_bytes())
    for args in (["dat", str(src)], ["raw", str(src)], ["raw", str(renamed)]):
        out = tmp_path / "back.h5"
        assert main(["convert", *args, "-o", str(out), "-q"]) == 0
        with psfmt.read(out) as capture:
            assert same(capture.events.read(), events) and (capture.events.width, capture.events.height) == (640, 480)
            lines = capture.description.splitlines()
            assert lines[1:] == [
                "geometry_source = Width 640, Height 480", "dat_header:", "% Data file containing CD events", "% Version 2",
                "% Width 640", "% Height 480", "% Date 2020-09-14 14:18:29",
            ]
        assert psfmt.validate(out).valid
        out.unlink()
    assert main(["convert", "dat", str(src), "-o", str(tmp_path / "small.h5"), "--geometry", "320x240", "-q"]) == 0
    with psfmt.read(tmp_path / "small.h5") as capture:
        inside = (events.x < 320) & (events.y < 240)
        assert same(capture.events.read(), events[inside]) and "geometry_source = --geometry 320x240" in capture.description
    # the DAT encoding of an EVT 3.0 recording's events, back through both converters, is the same capture
    raw = tmp_path / "rec.raw"
    evt3.write_raw(raw, [events[events.t < (1 << 30)]], 640, 480)
    assert main(["convert", "raw", str(raw), "-o", str(tmp_path / "raw.h5"), "-q"]) == 0
    with psfmt.read(tmp_path / "raw.h5") as capture:
        assert same(capture.events.read(), events[events.t < (1 << 30)])
