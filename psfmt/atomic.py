"""Atomic file replacement: write beside the target, then rename over it; and a lock for updates.

A rename replaces a file as a unit, but two processes that each copy a capture, add their result and
rename the copy back would keep only the last one: ``locked`` serialises such read-modify-replace
updates of one file across processes (POSIX ``flock`` on a hidden lock file beside it).
"""

from __future__ import annotations

import os
import secrets
import stat
from collections.abc import Iterable, Iterator
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


def check_target(
    target: str | os.PathLike[str], inputs: Iterable[str | os.PathLike[str]] = (), *, folder: bool = False
) -> Path:
    """``target`` as a Path, or a FormatError naming it when a write must not replace it — the one
    output-path rule of every command that writes:

    - it is a symbolic link (a rename would replace the link, a write through it the file it points
      to: neither is what was asked);
    - it exists and is not a regular file (``folder``: not a folder) — a device such as ``/dev/null``,
      a FIFO or a socket is never replaced by a file;
    - it is one of ``inputs`` (the same file through another name or a hard link: same device and
      inode), or with ``folder`` holds one of them, so an output never replaces what it is made from.
    """
    target = Path(target)
    try:
        info = os.lstat(target)
    except (FileNotFoundError, NotADirectoryError):
        return target
    if stat.S_ISLNK(info.st_mode):
        raise FormatError(target, "is a symbolic link; write to the file itself or to a new path")
    if folder and not stat.S_ISDIR(info.st_mode):
        raise FormatError(target, "exists and is not a folder")
    if not folder and stat.S_ISDIR(info.st_mode):
        raise FormatError(target, "is a folder, not a file")
    if not folder and not stat.S_ISREG(info.st_mode):
        raise FormatError(target, "exists and is not a regular file (a device, FIFO or socket); it is not replaced")
    for source in inputs:
        try:
            found = os.stat(source)
        except OSError:
            continue
        if (found.st_dev, found.st_ino) == (info.st_dev, info.st_ino) or (folder and _inside(source, target)):
            raise FormatError(target, f"is the input {source} (or holds it); write the output elsewhere")
    return target


def _inside(path: str | os.PathLike[str], folder: Path) -> bool:
    """Whether ``path`` lies inside ``folder`` once both are resolved."""
    try:
        return Path(path).resolve().is_relative_to(folder.resolve())
    except (OSError, RuntimeError):
        return False


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
