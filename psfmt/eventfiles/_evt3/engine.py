"""Which engine runs a kernel: the compiled loop (numba, when installed) or the vectorised numpy path."""

from __future__ import annotations

import functools
import importlib.util
import os
from collections.abc import Callable
from typing import Any

ENGINES = ("auto", "numba", "numpy")


@functools.cache
def _numba_installed() -> bool:
    # found, not imported: numba's import (with the scipy it loads) takes a fifth of a second that
    # reading a capture, or `pstoolkit info`, never needs
    return importlib.util.find_spec("numba") is not None


def has_numba() -> bool:
    """Whether the compiled engine can run (numba installed and not disabled by PSFMT_NUMBA=0)."""
    return _numba_installed() and os.environ.get("PSFMT_NUMBA", "1") != "0"


def usable_cores() -> int:
    """The CPU cores this process may run on (its affinity where the system reports one)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def resolve(engine: str) -> str:
    """``numba`` or ``numpy`` for one of ``ENGINES`` (``auto``: the compiled one when it can run);
    ValueError for another name, or for ``numba`` where it cannot run."""
    if engine not in ENGINES:
        raise ValueError(f"engine must be one of {', '.join(ENGINES)}, not {engine!r}")
    if engine == "numba" and not has_numba():
        raise ValueError("engine 'numba' asked for but numba is not installed (or PSFMT_NUMBA=0)")
    return ("numba" if has_numba() else "numpy") if engine == "auto" else engine


def jit(fn: Callable[..., Any]) -> Callable[..., Any]:
    """``fn`` compiled by numba (cached on disk, releasing the GIL) where numba is installed, else
    ``fn``. numba is imported and the kernel compiled (or loaded from the cache) on the first call,
    so that importing a codec loads no numba."""
    if not _numba_installed():
        return fn
    compiled: list[Callable[..., Any]] = []

    @functools.wraps(fn)
    def call(*args: Any) -> Any:
        if not compiled:
            import numba

            compiled.append(numba.njit(cache=True, nogil=True)(fn))
        return compiled[0](*args)

    return call
