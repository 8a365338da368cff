"""Issue 19, item 7: processes storing results in one capture at once lose none of them.

Real processes (multiprocessing, spawn), released together by a barrier so their read-modify-replace
updates overlap; without the lock most rounds keep only the last rename's result.
"""

from __future__ import annotations

import multiprocessing
from pathlib import Path
from typing import Any

import numpy as np
from helpers.captures import sample_capture

import psfmt

PROCESSES = 4
ROUNDS = 3


def store(path: str, name: str, barrier: Any) -> None:
    result = psfmt.Result(name, {"normal": np.full((64, 64, 3), len(name), np.float32)}, solver="x", options={"name": name})
    barrier.wait()
    psfmt.write_result(path, result)


def test_concurrent_stores_keep_every_result(tmp_path: Path) -> None:
    path = tmp_path / "capture.h5"
    psfmt.write(sample_capture("hybrid", seed=0, n_events=3000), path)
    context = multiprocessing.get_context("spawn")
    names: list[str] = []
    for round_ in range(ROUNDS):
        barrier = context.Barrier(PROCESSES)
        mine = [f"r{round_}-{k}" for k in range(PROCESSES)]
        workers = [context.Process(target=store, args=(str(path), name, barrier)) for name in mine]
        for worker in workers:
            worker.start()
        for worker in workers:
            worker.join(timeout=120)
        assert [w.exitcode for w in workers] == [0] * PROCESSES
        names += mine
    with psfmt.read(path, verify=True) as capture:
        assert sorted(capture.results) == sorted(names + ["eventps"])
        assert all(capture.results[name].options == {"name": name} for name in names)
    # no lock file or temporary file is left beside the capture
    assert sorted(p.name for p in tmp_path.iterdir()) == ["capture.h5"]
