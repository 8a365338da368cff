"""``pstoolkit._shared.worksharing``: every task is taken exactly once, from any number of threads."""

from __future__ import annotations

import numba
import numpy as np
import pytest

from pstoolkit._shared.worksharing import take_task


@numba.njit(parallel=True)
def _take_all(tasks: int, threads: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    taken = np.empty(1, np.int64)
    taken[0] = 0
    times = np.zeros(tasks, np.int64)
    per_worker = np.zeros(threads, np.int64)
    for worker in numba.prange(threads):
        while True:
            task = take_task(taken)
            if task >= tasks:
                break
            times[task] += 1
            per_worker[worker] += 1
    # the counter itself: a read of it here could be moved ahead of the loop (see take_task)
    return times, per_worker, taken


@numba.njit
def _take_in_turn(counter: np.ndarray, calls: int) -> np.ndarray:
    out = np.empty(calls, np.int64)
    for i in range(calls):
        out[i] = take_task(counter)
    return out


def test_calls_number_the_tasks_in_turn() -> None:
    counter = np.array([5, 99], np.int64)
    assert _take_in_turn(counter, 4).tolist() == [5, 6, 7, 8]
    assert counter.tolist() == [9, 99]


@pytest.mark.parametrize("threads", [1, 2, 7])
def test_every_task_is_taken_once(threads: int) -> None:
    times, per_worker, final = _take_all(1000, threads)
    assert (times == 1).all()
    assert per_worker.sum() == 1000
    # each worker's last call finds the tasks gone
    assert final.tolist() == [1000 + threads]


def test_other_counters_are_refused() -> None:
    with pytest.raises(numba.core.errors.TypingError):
        _take_in_turn(np.zeros(2), 1)
