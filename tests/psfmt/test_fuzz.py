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
import sys
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
CHILD_MB = 512
ARRAY_MB = 64
"""The reader may hold one array of ``PSFMT_MAX_ARRAY_BYTES`` whole; the test lowers it from 1 GiB so that the
children's bound measures the reader, not the limit."""
EXAMPLES = 30
PROC_STATUS = Path("/proc/self/status")


# The checking child reports its own peak resident memory: VmHWM of the process image after exec.
# (ru_maxrss from wait4 or RUSAGE_CHILDREN is no use: Linux carries the parent's resident size over
# the fork/vfork-and-exec into the child's figure, and the test process holds torch and more.)
PEAK_WRAPPER = """
import atexit, os, runpy, sys
def _peak():
    with open("/proc/self/status") as status:
        kb = next(int(line.split()[1]) for line in status if line.startswith("VmHWM:"))
    with open(os.environ["PSK_PEAK_FILE"], "a") as out:
        out.write(f"{kb}\\n")
atexit.register(_peak)
sys.argv = ["psfmt.isolate", *sys.argv[1:]]
runpy.run_module("psfmt.isolate", run_name="__main__", alter_sys=True)
"""


def measured_popen(peak_file: Path) -> type[subprocess.Popen]:
    """Popen that runs psfmt's checking child under ``PEAK_WRAPPER``, which appends its peak (kB) to
    ``peak_file``."""

    class Measured(subprocess.Popen):
        def __init__(self, args: list[str], *rest: object, env: dict[str, str] | None = None, **kwargs: object) -> None:
            if list(args[1:3]) == ["-m", "psfmt.isolate"]:
                args = [args[0], "-c", PEAK_WRAPPER, *args[3:]]
                env = {**(env if env is not None else os.environ), "PSK_PEAK_FILE": str(peak_file)}
            super().__init__(args, *rest, env=env, **kwargs)  # type: ignore[arg-type]

    return Measured


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
    monkeypatch.setenv("PSFMT_MAX_ARRAY_BYTES", str(ARRAY_MB << 20))
    folder = tmp_path_factory.mktemp("fuzz")
    peak_file = folder / "child-peaks.txt"
    if PROC_STATUS.exists():
        monkeypatch.setattr(isolate.subprocess, "Popen", measured_popen(peak_file))
    path = mutate(bases[kind], folder / "hostile.h5", kinds, seed)
    tracemalloc.start()
    start = time.perf_counter()
    try:
        probe(path)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert time.perf_counter() - start < SECONDS, (kind, kinds, seed)
    assert peak < CALLER_MB << 20, (kind, kinds, seed, peak)
    peaks_kb = [int(line) for line in peak_file.read_text().split()] if peak_file.exists() else []
    assert all(kb < CHILD_MB << 10 for kb in peaks_kb), (kind, kinds, seed, peaks_kb)


def test_the_long_run_runs_as_documented_and_writes_nothing_into_the_checkout() -> None:
    """Issue 33, item 16: ``python tests/fuzz/fuzz_captures.py --files N`` from the checkout, as
    docs/security.md gives it (``tests/psfmt`` must not shadow the package), leaves the tree as it was."""
    root = Path(__file__).resolve().parents[2]

    def tree() -> set[str]:
        return {str(p.relative_to(root)) for folder in ("tests", "benchmarks") for p in (root / folder).rglob("*")}

    before = tree()
    done = subprocess.run(
        [sys.executable, "tests/fuzz/fuzz_captures.py", "--files", "2", "--seed", "3"],
        cwd=root, capture_output=True, text=True, timeout=300, env={**os.environ, "PYTHONDONTWRITEBYTECODE": ""},
    )
    assert done.returncode == 0, done.stderr[-2000:]
    rows = dict(line.split() for line in done.stdout.splitlines()[1:7])
    assert sum(map(int, rows.values())) == 2 and rows["traceback"] == rows["hang"] == rows["crash"] == "0"
    assert tree() == before
