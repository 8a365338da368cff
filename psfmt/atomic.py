"""Atomic file replacement: write beside the target, then rename over it; and a lock for updates.

A rename replaces a file as a unit, but two processes that each copy a capture, add their result and
rename the copy back would keep only the last one: ``locked`` serialises such read-modify-replace
updates of one file across processes (POSIX ``flock`` on a hidden lock file beside it).
"""

from __future__ import annotations

import os
import secrets
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from psfmt.errors import FormatError

try:
    import fcntl
except ImportError:  # pragma: no cover - Windows has no flock
    fcntl = None  # type: ignore[assignment]


def temporary_sibling(target: str | os.PathLike[str]) -> Path:
    """A hidden, unique path in the target's folder, so the final rename never crosses file systems."""
    target = Path(target)
    return target.with_name(f".{target.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")


def commit(tmp: Path, target: str | os.PathLike[str]) -> None:
    """Flush ``tmp`` to disk and rename it over ``target`` in one step; a target that is a folder is a
    FormatError naming the target (not the hidden temporary file)."""
    with open(tmp, "rb") as fh:
        os.fsync(fh.fileno())
    try:
        os.replace(tmp, target)
    except IsADirectoryError:
        raise FormatError(target, "is a folder, not a file") from None


def check_target(target: str | os.PathLike[str]) -> Path:
    """``target`` as a Path, or a FormatError when a write could never replace it (it is a folder)."""
    target = Path(target)
    if target.is_dir():
        raise FormatError(target, "is a folder, not a file")
    return target


@contextmanager
def locked(target: str | os.PathLike[str]) -> Iterator[None]:
    """Hold the exclusive update lock of ``target`` for the block, waiting for other holders.

    The lock is an ``flock`` on ``.<name>.lock`` beside the target, removed by its holder before it
    lets go; a waiter that then gets the lock of the removed file sees that and locks anew, so the
    lock file never outlives an update. Only processes that take this lock are kept out. Where the
    system has no ``flock`` (Windows) the block runs unlocked.
    """
    target = Path(target)
    if fcntl is None:  # pragma: no cover - Windows
        yield
        return
    lock = target.with_name(f".{target.name}.lock")
    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
            try:
                current = os.stat(lock).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:
                current = False
        except BaseException:
            os.close(fd)
            raise
        if current:
            break
        os.close(fd)
    try:
        yield
    finally:
        lock.unlink(missing_ok=True)
        os.close(fd)


@contextmanager
def atomic_path(target: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path to write; on success it replaces ``target``, on any exception
    (Ctrl-C included) it is removed and ``target`` is left as it was."""
    tmp = temporary_sibling(check_target(target))
    try:
        yield tmp
        commit(tmp, target)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
