"""Which engine runs a kernel: the compiled loop (numba, when installed) or the vectorised numpy path."""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

try:  # the compiled fast path is optional: psfmt must work with numpy and h5py alone
    import numba
except ImportError:  # pragma: no cover - exercised where numba is absent
    numba = None

ENGINES = ("auto", "numba", "numpy")


def has_numba() -> bool:
    """Whether the compiled engine can run (numba installed and not disabled by PSFMT_NUMBA=0)."""
    return numba is not None and os.environ.get("PSFMT_NUMBA", "1") != "0"


def resolve(engine: str) -> str:
    """``numba`` or ``numpy`` for one of ``ENGINES`` (``auto``: the compiled one when it can run);
    ValueError for another name, or for ``numba`` where it cannot run."""
    if engine not in ENGINES:
        raise ValueError(f"engine must be one of {', '.join(ENGINES)}, not {engine!r}")
    if engine == "numba" and not has_numba():
        raise ValueError("engine 'numba' asked for but numba is not installed (or PSFMT_NUMBA=0)")
    return ("numba" if has_numba() else "numpy") if engine == "auto" else engine


def jit(fn: Callable[..., Any]) -> Callable[..., Any]:
    """``fn`` compiled by numba (cached on disk, releasing the GIL) where numba is installed, else ``fn``."""
    return numba.njit(cache=True, nogil=True)(fn) if numba is not None else fn
