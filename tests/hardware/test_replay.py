"""The ``replay`` source: frames, events and triggers in time order, exactly as recorded; triggers
derived from the light model; real-time pacing; clear errors. ``write_recording`` is the small
hybrid recording the hardware tests replay."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from helpers.replay import PERIOD_US, write_recording

import psfmt
from pstoolkit.errors import UserError
from pstoolkit.hardware.backend import (
    CameraSource,
    EventBlock,
    FrameBlock,
    Sweep,
    TriggerBlock,
    backend_class,
)
from pstoolkit.plugin.manager import get_registries


def _replay(path: Path, **options: object) -> CameraSource:
    entry = get_registries().backends.get("replay")
    cls = backend_class(entry, "source")
    pairs = [f"{k}={v}" for k, v in {"speed": 0, **options}.items()]
    return cls(str(path), entry.parse_options(pairs))


def test_replay_plays_frames_events_and_triggers_in_time_order(tmp_path: Path) -> None:
    rec = write_recording(tmp_path / "rec.h5")
    with _replay(rec, slice_us=700) as source, psfmt.load(rec) as original:
        assert source.period_us == PERIOD_US
        assert source.frame_sensor is not None and (source.frame_sensor.height, source.frame_sensor.channels) == (32, 3)
        assert source.event_sensor is not None and source.event_sensor.contrast_pos == 0.15
        packets = list(source.stream(Sweep(PERIOD_US)))
    times = [p.t_us for p in packets]
    assert times == sorted(times)
    frames = [p for p in packets if isinstance(p, FrameBlock)]
    assert np.array_equal(np.concatenate([f.data for f in frames]), np.asarray(original.frames.data))
    assert np.array_equal(np.concatenate([f.t_end_us for f in frames]), original.frames.t_end_us)
    played = psfmt.EventArray.concatenate([p.events for p in packets if isinstance(p, EventBlock)])
    recorded = original.events.read()
    for c in "xytp":
        assert np.array_equal(getattr(played, c), getattr(recorded, c))
    for p in packets:  # an event block holds only events of its slice
        if isinstance(p, EventBlock):
            assert p.t_end_us - 700 <= p.events.t[0] and p.events.t[-1] < p.t_end_us
    triggers = [p for p in packets if isinstance(p, TriggerBlock)]
    t = np.concatenate([b.t for b in triggers])
    value = np.concatenate([b.value for b in triggers])
    assert t.tolist() == [0, 10, 6000, 6010, 12000, 12010] and value.tolist() == [1, 0, 1, 0, 1, 0]


def test_replay_keeps_real_time_when_asked(tmp_path: Path) -> None:
    rec = write_recording(tmp_path / "rec.h5")  # 12 ms of recording
    with _replay(rec, speed=0.5) as source:
        start = time.perf_counter()
        last = list(source.stream(Sweep(PERIOD_US)))[-1]
        elapsed = time.perf_counter() - start
    assert elapsed >= (last.t_us / 1e6) / 0.5  # 24 ms of wall time at half speed


def test_replay_errors_are_one_line(tmp_path: Path) -> None:
    with pytest.raises(UserError, match=r"^replay .*missing\.h5: does not exist$"):
        with _replay(tmp_path / "missing.h5"):
            pass
    rec = write_recording(tmp_path / "rec.h5")
    with _replay(rec) as source:
        with pytest.raises(UserError, match=r"recorded with a 6000 µs light period, but the light is set to 5000 µs$"):
            next(source.stream(Sweep(5000)))
    classic = psfmt.Capture(
        frames=psfmt.Frames(np.zeros((3, 8, 8, 3), np.uint8), light_direction=np.eye(3), light_intensity=np.ones((3, 3)))
    )
    psfmt.write(classic, tmp_path / "classic.h5")
    with pytest.raises(UserError, match=r"its frames have no exposure windows"):
        with _replay(tmp_path / "classic.h5"):
            pass
    entry = get_registries().backends.get("replay")
    with pytest.raises(UserError, match=r"^backend 'replay' is a source, not a light$"):
        backend_class(entry, "light")
