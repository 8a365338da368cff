"""Atomic writes: a failure or Ctrl-C mid-write leaves no file at the target, an existing target
byte-identical, and no temporary file behind."""

from __future__ import annotations

import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from helpers.captures import sample_capture, sample_events
from helpers.interrupt import interruptible

import psfmt
from psfmt.atomic import commit

INTERRUPTS = [RuntimeError("disk on fire"), KeyboardInterrupt()]


def listing(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


@pytest.fixture(params=[False, True], ids=["no target", "existing target"])
def target(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[tuple[Path, bytes | None]]:
    """The path to write and, when a file is already there, its bytes (which must survive)."""
    path = tmp_path / "capture.h5"
    before = None
    if request.param:
        psfmt.write(sample_capture("events", seed=9), path)
        before = path.read_bytes()
    yield path, before


def assert_untouched(path: Path, before: bytes | None) -> None:
    if before is None:
        assert listing(path.parent) == []
    else:
        assert listing(path.parent) == [path.name]
        assert path.read_bytes() == before


class FailingEventSource:
    """An event source (like a camera driver) that delivers one block, then fails."""

    def __init__(self, error: BaseException) -> None:
        self.error = error
        self.block = sample_events(500, seed=1)

    def __len__(self) -> int:
        return 1000

    @property
    def t_first_us(self) -> int:
        return int(self.block.t[0])

    @property
    def t_last_us(self) -> int:
        return int(self.block.t[-1])

    def chunks(self) -> Iterator[psfmt.EventArray]:
        yield self.block
        raise self.error


class FailingFrameSource:
    """Frames read from a device that fails on the second frame."""

    shape = (3, 16, 16, 3)
    dtype = np.dtype(np.uint8)

    def __init__(self, error: BaseException) -> None:
        self.error = error

    def __getitem__(self, index: Any) -> np.ndarray:
        if index != 0:
            raise self.error
        return np.zeros(self.shape[1:], self.dtype)


class FailingMap:
    """A result map whose conversion to an array fails (a solver interrupted while handing over)."""

    def __init__(self, error: BaseException) -> None:
        self.error = error

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        raise self.error


@pytest.mark.parametrize("error", INTERRUPTS, ids=["exception", "ctrl-c"])
def test_streaming_writer_block_that_fails_leaves_nothing(target: tuple[Path, bytes | None], error: BaseException) -> None:
    path, before = target
    with pytest.raises(type(error)):
        with psfmt.CaptureWriter(path) as writer:
            writer.append_frames(np.zeros((2, 16, 16, 3), np.uint8), t_start_us=[0, 10], t_end_us=[10, 20])
            writer.begin_events(16, 16)
            writer.append_events(sample_events(100_000, seed=2, width=16, height=16))
            assert len(listing(path.parent)) == (1 if before is None else 2)
            raise error
    assert_untouched(path, before)


@pytest.mark.parametrize("error", INTERRUPTS, ids=["exception", "ctrl-c"])
@pytest.mark.parametrize("part", ["events", "frames"])
def test_write_that_fails_midway_leaves_nothing(target: tuple[Path, bytes | None], error: BaseException, part: str) -> None:
    path, before = target
    if part == "events":
        capture = psfmt.Capture(events=psfmt.Events(32, 32, FailingEventSource(error)))  # type: ignore[arg-type]
    else:
        frames = psfmt.Frames(FailingFrameSource(error), t_start_us=[0, 1, 2], t_end_us=[1, 2, 3])  # type: ignore[arg-type]
        capture = psfmt.Capture(frames=frames)
    with pytest.raises(type(error)):
        psfmt.write(capture, path)
    assert_untouched(path, before)


@pytest.mark.parametrize("error", INTERRUPTS, ids=["exception", "ctrl-c"])
def test_write_result_that_fails_leaves_the_capture_as_it_was(tmp_path: Path, error: BaseException) -> None:
    path = tmp_path / "capture.h5"
    psfmt.write(sample_capture("hybrid", seed=3), path)
    before = path.read_bytes()
    result = psfmt.Result("broken", {"normal": FailingMap(error)}, solver="broken")  # type: ignore[dict-item]
    with pytest.raises(type(error)):
        psfmt.write_result(path, result)
    assert_untouched(path, before)


def test_a_folder_at_the_target_is_named_and_left_alone(tmp_path: Path) -> None:
    """Issue 19, item 15: a folder where the file should go is reported under its own name (not the
    hidden temporary file's), before anything is written, and also when it appears at the rename."""
    path = tmp_path / "capture.h5"
    path.mkdir()
    (path / "keep").write_text("x")
    with pytest.raises(psfmt.FormatError) as caught:
        psfmt.write(sample_capture("events", seed=1), path)
    assert str(caught.value) == f"{path}: is a folder, not a file"
    assert listing(tmp_path) == ["capture.h5"] and listing(path) == ["keep"]
    tmp = tmp_path / ".late.tmp"
    tmp.write_text("data")
    with pytest.raises(psfmt.FormatError) as caught:
        commit(tmp, path)
    assert str(caught.value) == f"{path}: is a folder, not a file"


def test_atomic_path_on_interrupt(tmp_path: Path) -> None:
    path = tmp_path / "notes.txt"
    path.write_text("old")
    with pytest.raises(KeyboardInterrupt):
        with psfmt.atomic_path(path) as tmp:
            assert tmp.parent == tmp_path and tmp.name.startswith(".notes.txt.") and tmp.name.endswith(".tmp")
            tmp.write_text("new")
            raise KeyboardInterrupt
    assert listing(tmp_path) == ["notes.txt"] and path.read_text() == "old"
    with psfmt.atomic_path(path) as tmp:
        tmp.write_text("new")
    assert listing(tmp_path) == ["notes.txt"] and path.read_text() == "new"


def test_missing_folder_is_a_one_line_error(tmp_path: Path) -> None:
    with pytest.raises(psfmt.FormatError) as caught:
        psfmt.write(sample_capture("events"), tmp_path / "no" / "c.h5")
    assert str(caught.value) == f"{tmp_path / 'no' / 'c.h5'}: folder {tmp_path / 'no'} does not exist"


CHILD = """
import sys, time
import numpy as np
import psfmt

with psfmt.CaptureWriter(sys.argv[1]) as writer:
    writer.begin_events(32, 32)
    for i in range(100_000):
        t = np.arange(1000, dtype=np.int64) + 1000 * i
        writer.append_events(psfmt.EventArray(t % 32, t % 32, t, np.ones(1000)))
        if i == 5:
            print("writing", flush=True)
        time.sleep(0.002)
"""


@pytest.mark.parametrize("existing", [False, True], ids=["no target", "existing target"])
def test_real_ctrl_c_in_a_writing_process(tmp_path: Path, existing: bool) -> None:
    path = tmp_path / "capture.h5"
    before = None
    if existing:
        psfmt.write(sample_capture("events", seed=4), path)
        before = path.read_bytes()
    child = interruptible([sys.executable, "-c", CHILD, str(path)], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        assert child.stdout is not None and child.stdout.readline() == b"writing\n"
        child.send_signal(signal.SIGINT)
        _, err = child.communicate(timeout=30)
    finally:
        if child.poll() is None:
            child.kill()
    assert child.returncode != 0 and b"KeyboardInterrupt" in err
    assert_untouched(path, before)
