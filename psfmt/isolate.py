"""Checking a file in a child process, so that a hostile file can neither hang nor crash the caller.

HDF5 is C: a crafted file can send it into a loop that never returns (HDF5 2.0 decoding a global heap
whose objects were corrupted loops for ever on one flipped bit) or into a crash, and there no Python
signal or thread reaches it. ``inspect`` runs the checks the reader and the validator share
(``psfmt._validate.checks.inspect``) in a child python that reports its progress as it reads; a child that
says nothing for ``QUIET_S`` seconds is killed, one that dies is reported, and either way the file is
a one-line FormatError ("damaged HDF5 file …"). The child's memory is capped too. A file the child
has checked is then read by the caller: HDF5 parses the same structures the same way, so it reads.

Isolation is on inside ``isolated()`` (the ``pstoolkit`` command runs in it) and wherever the
environment variable ``PSFMT_ISOLATE`` is ``1``; ``PSFMT_ISOLATE=0`` turns it off everywhere.

    python -m psfmt.isolate FILE CONTENT MEMORY_BYTES   # the child: JSON lines on stdout
"""

from __future__ import annotations

import json
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, fields
from pathlib import Path
from typing import Any

from psfmt._validate import checks
from psfmt._validate.findings import Finding
from psfmt.errors import FormatError
from psfmt.files import open_hdf5
from psfmt.limits import Limits

QUIET_S = 60.0
"""A child that reports no progress for this long is stuck in HDF5 (a scan reports every 16 MiB)."""
BASE_MEMORY_BYTES = 2 << 30
"""The child's address space beyond the arrays it may read (the interpreter, numpy, HDF5's caches)."""
ENV = "PSFMT_ISOLATE"
_PROGRESS_EVERY_S = 0.2
_state = {"on": False}


def enabled() -> bool:
    """Whether reads and validations check files in a child process (``PSFMT_ISOLATE`` decides where set)."""
    value = os.environ.get(ENV)
    return value.strip() not in ("", "0") if value is not None else _state["on"]


def wanted(choice: bool | None) -> bool:
    """A caller's ``isolate_check`` argument: its choice, or ``enabled()`` when it made none."""
    return enabled() if choice is None else choice


@contextmanager
def isolated(on: bool = True) -> Iterator[None]:
    """Within the block, ``psfmt.read`` and ``psfmt.validate`` check files in a child process."""
    before = _state["on"]
    _state["on"] = on
    try:
        yield
    finally:
        _state["on"] = before


def memory_bytes(limits: Limits) -> int:
    """The child's address-space cap: a scan holds at most a few arrays of ``max_array_bytes``."""
    return BASE_MEMORY_BYTES + 3 * limits.max_array_bytes


def _environment(limits: Limits) -> dict[str, str]:
    env = dict(os.environ)
    for f in fields(limits):
        env[f"PSFMT_{f.name.upper()}"] = str(getattr(limits, f.name))
    env[ENV] = "0"
    env.setdefault("OMP_NUM_THREADS", "1")
    env.setdefault("OPENBLAS_NUM_THREADS", "1")
    return env


def _lines(stream: Any, into: queue.Queue[str | None]) -> None:
    for line in stream:
        into.put(line)
    into.put(None)


def inspect(
    path: str | os.PathLike[str], *, content: bool, limits: Limits | None = None, progress: Any = None, quiet_s: float | None = None
) -> list[Any]:
    """``psfmt._validate.checks.inspect`` on the file at ``path``, run in a child process: the findings, or the
    FormatError it raised. A child silent for ``quiet_s`` seconds, or one that dies, makes the file
    "damaged" (``quiet_s`` defaults to ``QUIET_S``). ``progress(fraction, message)`` hears the
    child's progress."""
    quiet_s = QUIET_S if quiet_s is None else quiet_s
    path = Path(path)
    limits = limits or Limits.from_env()
    command = [sys.executable, "-m", "psfmt.isolate", str(path), "1" if content else "0", str(memory_bytes(limits))]
    child = subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL, text=True, env=_environment(limits)
    )
    lines: queue.Queue[str | None] = queue.Queue()
    errors: queue.Queue[str | None] = queue.Queue()
    for stream, into in ((child.stdout, lines), (child.stderr, errors)):
        threading.Thread(target=_lines, args=(stream, into), daemon=True).start()
    answer: dict[str, Any] | None = None
    try:
        while True:
            try:
                line = lines.get(timeout=quiet_s)
            except queue.Empty:
                child.kill()
                raise FormatError(path, f"damaged HDF5 file (HDF5 made no progress reading it for {quiet_s:g} s)") from None
            if line is None:
                break
            message = json.loads(line)
            if "progress" in message:
                if progress is not None:
                    progress(message["progress"], message["message"])
            else:
                answer = message
        code = child.wait()
    except BaseException:
        child.kill()
        child.wait()
        raise
    if answer is None:
        if code < 0:
            name = signal.Signals(-code).name
            raise FormatError(path, f"damaged HDF5 file (HDF5 crashed reading it: {name})")
        text = "".join(iter(lambda: errors.get(timeout=5) or "", ""))
        raise RuntimeError(f"psfmt's check of {path} failed (exit code {code}):\n{text.strip()}")
    if "error" in answer:
        raise FormatError(path, answer["error"])
    return [Finding(**finding) for finding in answer["findings"]]


def _child(argv: list[str]) -> None:
    """The child: check ``argv[0]`` and print progress and the answer as JSON lines."""
    path, content, memory = Path(argv[0]), argv[1] == "1", int(argv[2])
    try:
        import resource

        resource.setrlimit(resource.RLIMIT_AS, (memory, memory))
    except (ImportError, ValueError, OSError):  # no rlimits on this system: the time limit still holds
        pass

    last = [0.0]

    def progress(fraction: float, message: str) -> None:
        now = time.monotonic()
        if now - last[0] >= _PROGRESS_EVERY_S or fraction >= 1.0:
            last[0] = now
            print(json.dumps({"progress": fraction, "message": message}), flush=True)

    try:
        progress(0.0, "structure")
        with open_hdf5(path) as f:
            findings = checks.inspect(f, path, content=content, progress=progress)
        answer: dict[str, Any] = {"findings": [asdict(finding) for finding in findings]}
    except FormatError as exc:
        answer = {"error": exc.message}
    except MemoryError:
        answer = {"error": f"damaged HDF5 file (reading it needs more than {memory:,} bytes of memory)"}
    print(json.dumps(answer), flush=True)


if __name__ == "__main__":
    _child(sys.argv[1:])
