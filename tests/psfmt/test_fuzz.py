"""Issue 19: a seeded property test of the reader on hostile variants of small captures.

Hypothesis draws a base capture and one to three mutations (``mutations.MUTATIONS``); every file must
give a validation report or one FormatError, the reader must agree with the validator and read a valid
file completely, never a traceback, within ``SECONDS`` each, the caller's Python and numpy
allocations under ``CALLER_MB`` and the checking child processes under ``CHILD_MB``. The long run is
``tests/fuzz/fuzz_captures.py``.
"""

from __future__ import annotations

import os
import subprocess
import time
import tracemalloc
from pathlib import Path

import pytest
from helpers.mutations import BASES, MUTATIONS, base_capture, mutate, probe
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from psfmt import isolate

SECONDS = 20.0
CALLER_MB = 64
CHILD_MB = 1024
EXAMPLES = 30


class MeasuredPopen(subprocess.Popen):
    """Popen that reaps its child with ``os.wait4`` and keeps the child's own peak RSS (kB on Linux):
    ``RUSAGE_CHILDREN`` is a high-water mark over every child the test process ever waited for (Dask
    workers of other tests included), so it cannot bound the reader's children alone."""

    peaks_kb: list[int] = []

    def _try_wait(self, wait_flags: int) -> tuple[int, int]:  # CPython's hook around waitpid
        try:
            pid, status, usage = os.wait4(self.pid, wait_flags)
        except ChildProcessError:
            return self.pid, 0
        if pid == self.pid:
            MeasuredPopen.peaks_kb.append(usage.ru_maxrss)
        return pid, status


@pytest.fixture(scope="module")
def bases(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("fuzz-bases")
    return {kind: base_capture(folder / f"{kind}.h5", kind) for kind in BASES}


@settings(max_examples=EXAMPLES, derandomize=True, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    kind=st.sampled_from(BASES),
    kinds=st.lists(st.sampled_from(sorted(MUTATIONS)), min_size=1, max_size=3),
    seed=st.integers(0, 2**32 - 1),
)
def test_hostile_variants_give_a_clean_answer(
    bases: dict[str, Path], tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch, kind: str, kinds: list[str], seed: int
) -> None:
    monkeypatch.setattr(isolate, "QUIET_S", 10.0)
    monkeypatch.setattr(isolate.subprocess, "Popen", MeasuredPopen)
    MeasuredPopen.peaks_kb.clear()
    path = mutate(bases[kind], tmp_path_factory.mktemp("fuzz") / "hostile.h5", kinds, seed)
    tracemalloc.start()
    start = time.perf_counter()
    try:
        probe(path)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert time.perf_counter() - start < SECONDS, (kind, kinds, seed)
    assert peak < CALLER_MB << 20, (kind, kinds, seed, peak)
    assert MeasuredPopen.peaks_kb and max(MeasuredPopen.peaks_kb) < CHILD_MB << 10, (kind, kinds, seed, MeasuredPopen.peaks_kb)
