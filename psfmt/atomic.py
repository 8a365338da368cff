"""Atomic file replacement: write beside the target, then rename over it."""

from __future__ import annotations

import os
import secrets
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


def temporary_sibling(target: str | os.PathLike[str]) -> Path:
    """A hidden, unique path in the target's folder, so the final rename never crosses file systems."""
    target = Path(target)
    return target.with_name(f".{target.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")


def commit(tmp: Path, target: str | os.PathLike[str]) -> None:
    """Flush ``tmp`` to disk and rename it over ``target`` in one step."""
    with open(tmp, "rb") as fh:
        os.fsync(fh.fileno())
    os.replace(tmp, target)


@contextmanager
def atomic_path(target: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path to write; on success it replaces ``target``, on any exception
    (Ctrl-C included) it is removed and ``target`` is left as it was."""
    tmp = temporary_sibling(target)
    try:
        yield tmp
        commit(tmp, target)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
