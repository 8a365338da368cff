"""The Python side of the format (issue 24, part C, item 2): ``len`` and slicing of event streams
and frames, loaded and lazy alike, windows given backwards refused, one-line reprs that never print
arrays, and the PEP 561 markers."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import REPO
from helpers.captures import sample_capture

import psfmt
import pstoolkit
from psfmt.events import H5EventStore

if sys.version_info >= (3, 11):
    import tomllib
else:  # Python 3.10: tomli is the same parser
    import tomli as tomllib

REPR_LIMIT = 300


@pytest.fixture(scope="module")
def hybrid_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("api") / "hybrid.h5"
    psfmt.write(sample_capture("hybrid", n_events=5000), path)
    return path


def _same(a: psfmt.EventArray, b: psfmt.EventArray) -> bool:
    return all(np.array_equal(getattr(a, c), getattr(b, c)) for c in "xytp")


def test_len_and_slices_of_events_and_frames_loaded_and_lazy(hybrid_file: Path) -> None:
    loaded = psfmt.load(hybrid_file)
    with psfmt.read(hybrid_file) as lazy:
        assert isinstance(lazy.events.data, H5EventStore)
        for capture in (loaded, lazy):
            assert len(capture.frames) == 3 and len(capture.events) == 5000
            head = capture.events[0:10]
            assert type(head) is psfmt.Events and (head.width, head.height, len(head)) == (32, 32, 10)
            assert _same(head.read(), loaded.events.data[0:10])
            for part in (slice(4990, None), slice(None, None, 7), slice(100, 10, -3), slice(10, 2), slice(-5, None)):
                assert _same(capture.events[part].read(), loaded.events.data[part]), part
                assert _same(capture.events.data[part], loaded.events.data[part]), part
        events = loaded.events.data
        assert type(events[0:10]) is psfmt.EventArray and len(events[0:10]) == 10
        assert type(lazy.events.data[0:10]) is psfmt.EventArray
        for stream in (lazy.events, events, lazy.events.data):
            with pytest.raises(TypeError, match=r"ev\[i:i\+1\]"):
                stream[3]  # type: ignore[index]


def test_a_window_given_backwards_raises_instead_of_reading_nothing(hybrid_file: Path) -> None:
    loaded = psfmt.load(hybrid_file)
    with psfmt.read(hybrid_file) as lazy:
        for stream in (lazy.events, lazy.events.data, loaded.events, loaded.events.data):
            with pytest.raises(ValueError, match=re.escape("event window [2000, 1000) µs ends before it starts: give t0_us <= t1_us")):
                stream.window(2000, 1000)
            assert len(stream.window(1000, 1000)) == 0
            assert _same(stream.window(np.int64(1000), np.int64(2000)), loaded.events.data.window(1000, 2000))


def test_reprs_are_one_short_line_of_facts(hybrid_file: Path) -> None:
    """``repr(capture)`` ran to 8,411 characters of numbers: every part now says what it holds in
    one line under ``REPR_LIMIT`` characters, on a loaded and on a lazy (even closed) capture."""
    loaded = psfmt.load(hybrid_file)
    lazy = psfmt.read(hybrid_file)
    expected = {
        "capture": ("Capture(hybrid, ", "hybrid.h5", "frames 3 × 64×64×3 uint8", "5000 events 32×32", "lights 'ring'", "ground truth",
                    "results: eventps"),
        "frames": ("Frames(3 × 64×64×3 uint8", "8-bit", "exposure windows"),
        "events": ("Events(32×32, 5000 events",),
        "ground_truth": ("GroundTruth(64×64: normal, mask, albedo, depth; materials ",),
        "calibration": ("Calibration(orthographic", "contrast +0.15/−0.2", "refractory 500 µs", "rate-limited"),
        "lights": ("LightSpec('ring', elevation_deg=43", "intensity=float64[3]"),
    }
    for capture in (loaded, lazy):
        for part, facts in expected.items():
            text = repr(capture if part == "capture" else getattr(capture, part))
            assert "\n" not in text and len(text) < REPR_LIMIT, text
            assert all(fact in text for fact in facts), (text, facts)
        result = repr(capture.results["eventps"])
        assert result.startswith("Result('eventps', solver 'eventps', maps: ") and "1.25 s" in result
    assert repr(loaded.events.data).startswith("EventArray(5000 events, t ") and repr(loaded.events).endswith("in memory)")
    assert repr(lazy.events).endswith("on disk)") and repr(lazy.frames.data) == "FrameStack(uint8[3, 64, 64, 3] on disk)"
    assert repr(loaded.triggers) == "Triggers(2 edges)" and repr(lazy.triggers).startswith("H5Triggers(2 edges in ")
    lazy.close()
    assert "hybrid.h5" in repr(lazy) and "on disk" in repr(lazy.events)  # no file access in a repr


def test_reprs_stay_bounded_whatever_a_file_names(hybrid_file: Path) -> None:
    capture = psfmt.load(hybrid_file)
    long_name = "r" * 500 + "\x1b]0;title\x07"
    capture.results = {f"{long_name}{i}": psfmt.Result(f"{long_name}{i}", {"normal": np.zeros((2, 2, 3))}, long_name) for i in range(40)}
    capture.lights = psfmt.LightSpec(long_name, {f"{long_name}{i}": np.zeros((100, 3)) for i in range(30)})
    capture.path = Path("/" + "d" * 400) / "capture.h5"
    for thing in (capture, capture.lights, *list(capture.results.values())[:2]):
        text = repr(thing)
        assert len(text) < REPR_LIMIT and "\x1b" not in text and "\n" not in text, text
    assert "+37 more" in repr(capture) and repr(capture).count("…") >= 3 and "capture.h5'" in repr(capture)
    assert "+24 more" in repr(capture.lights)


def test_the_packages_ship_their_pep_561_markers() -> None:
    for package in (psfmt, pstoolkit):
        assert (Path(package.__file__).parent / "py.typed").is_file(), package.__name__
    data = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]
    assert data["psfmt"] == ["py.typed"] and data["pstoolkit"] == ["py.typed"]
    assert "pstoolkit.view" in data  # the viewer's page is still declared
