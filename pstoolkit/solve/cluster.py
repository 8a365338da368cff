"""Dask distributed for the commands that fan work out (``batch``'s pairs, a tiled solver's tiles):
the machine's cores and memory, a quiet local cluster, and a client of it or of a running scheduler."""

from __future__ import annotations

import logging
import os
import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from pstoolkit.errors import UserError

# cgroup v2's limit of the memory this process's group may use ("max": none).
CGROUP_MEMORY_MAX = Path("/sys/fs/cgroup/memory.max")


def available_memory_bytes() -> int:
    """Physical memory this process may use: the machine's, or its cgroup's limit when lower."""
    total = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    try:
        limit = CGROUP_MEMORY_MAX.read_text().strip()
    except OSError:
        return total
    return min(total, int(limit)) if limit.isdigit() else total


PER_CORE = 4
"""Workers or threads per core at most (``max_parallel``)."""


def max_parallel() -> int:
    """The most worker processes or threads one job is given on this machine: ``PER_CORE`` per core
    this process may use. More would only queue for the cores, each one costing memory (a worker
    process about 100 MB before it loads a capture)."""
    return PER_CORE * available_cpus()


def check_workers(scheduler: str | None, workers: int | None) -> None:
    """UserError for ``workers`` below 1 or above ``max_parallel``, or given with a ``scheduler``
    (which has its own workers)."""
    if workers is None:
        return
    if scheduler is not None:
        raise UserError("--workers: only for the local cluster; an existing scheduler (--scheduler) has its own workers")
    if workers < 1:
        raise UserError(f"--workers {workers}: need at least one worker")
    if workers > max_parallel():
        raise UserError(
            f"--workers {workers}: more than this machine can run ({max_parallel()}: {PER_CORE} per core for its {available_cpus()} cores)"
        )


def connect(scheduler: str | None, workers: int | None) -> tuple[Any, Any]:
    """A ``distributed.Client`` of the scheduler at ``scheduler``, or of a new LocalCluster of
    ``workers`` processes (default: one per core; returned too, to close it; None for an existing
    scheduler). UserError when the scheduler cannot be reached, or for ``workers`` with a scheduler."""
    from distributed import Client  # deferred: loading dask takes a second that other commands never need

    check_workers(scheduler, workers)
    if scheduler is None:
        cluster = local_cluster(workers)
        client = Client(cluster, set_as_default=False)
        client.run(quiet_worker_logs)
        return client, cluster
    try:
        return Client(scheduler, timeout="20s", set_as_default=False), None
    except (OSError, ValueError, TypeError) as exc:
        raise UserError(f"--scheduler {scheduler!r}: cannot connect ({exc})") from None


def available_cpus() -> int:
    """CPU cores this process may use (the affinity mask where the system has one)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


@contextmanager
def quiet_loop_errors() -> Iterator[None]:
    """Silence the callback errors of the client's event loop (tornado's ``tornado.application``
    logger) for the block: they are Dask's own slips — a Ctrl-C while the client waits makes
    distributed's cancel callback log a NameError traceback — and a pair that fails is reported as
    its outcome anyway. After an exception (a Ctrl-C) they stay silenced: the loop's thread runs the
    cancel callbacks after the block has been left, while the process ends."""
    import distributed  # noqa: F401  (its import applies dask's logging config, which resets this logger's level)

    logger = logging.getLogger("tornado.application")
    level = logger.level
    logger.setLevel(logging.CRITICAL)
    yield
    logger.setLevel(level)


def local_cluster(workers: int | None = None) -> Any:
    """A ``LocalCluster`` of ``workers`` processes (default: one per available core) with one thread
    each, so a worker holds one capture at a time; each worker takes a task only when it is idle, so a
    worker that dies takes down only the pair it was running.

    Ctrl-C (SIGINT, which a terminal sends to every process of the command) reaches this process
    only, which cancels the tasks and closes the cluster: the user sees one line, not every worker's
    traceback. Where it can (``_quiet_forkserver``), the workers are forked from a fork server that
    ignores SIGINT, which they inherit."""
    import dask  # deferred: only batch runs need dask
    from distributed import LocalCluster

    check_workers(None, workers)
    count = available_cpus() if workers is None else workers
    settings: dict[str, Any] = {"distributed.scheduler.worker-saturation": 1.0}
    if _quiet_forkserver():
        settings["distributed.worker.multiprocessing-method"] = "forkserver"
    with dask.config.set(settings):
        # the scheduler serves HTTP whatever the dashboard: on a free port of this machine only (its
        # default, 8787 on every interface, warns when taken and is reachable from the network).
        return LocalCluster(
            n_workers=count, threads_per_worker=1, processes=True, dashboard_address="127.0.0.1:0", silence_logs=logging.ERROR
        )


def quiet_worker_logs() -> None:
    """Run in each worker of the local cluster (``Client.run``): Dask's own logs there up to
    CRITICAL. A worker still heartbeating while a Ctrl-C closes the cluster logs its broken stream as
    an ERROR traceback on the command's stderr; a pair that fails is reported as its outcome."""
    logging.getLogger("distributed").setLevel(logging.CRITICAL)


def _quiet_forkserver() -> bool:
    """Start multiprocessing's fork server with SIGINT ignored, which every process it forks inherits
    (a signal handler or mask would not survive); False where that cannot be done: no fork server
    (Windows), not the main thread, or a fork server already running."""
    import multiprocessing
    import multiprocessing.forkserver

    import dask
    from distributed.utils import get_mp_context

    if "forkserver" not in multiprocessing.get_all_start_methods() or threading.current_thread() is not threading.main_thread():
        return False
    server = multiprocessing.forkserver._forkserver  # type: ignore[attr-defined]
    if server._forkserver_pid is not None:
        return False
    with dask.config.set({"distributed.worker.multiprocessing-method": "forkserver"}):
        get_mp_context()  # sets the modules the server imports once for every worker
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        # the server process is started here (milliseconds); it imports its modules on its own
        multiprocessing.forkserver.ensure_running()
    finally:
        signal.signal(signal.SIGINT, previous)
    return True
