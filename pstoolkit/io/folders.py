"""Folders written as a unit: filled under a temporary name beside the target, then renamed into
place, so a folder by the target's name is always complete (``pstoolkit batch``'s result folders,
``pstoolkit export --frames``)."""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from psfmt.atomic import check_target, temporary_sibling


def replace_folder(new: Path, folder: Path) -> None:
    """Rename ``new`` to ``folder``; an existing ``folder`` is moved aside first and then removed.
    A ``folder`` that is a link or not a folder is a FormatError (``psfmt.atomic.check_target``)."""
    check_target(folder, folder=True)
    old = temporary_sibling(folder) if folder.exists() else None
    if old is not None:
        os.replace(folder, old)
    os.replace(new, folder)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


@contextmanager
def atomic_folder(target: Path) -> Iterator[Path]:
    """Yield a new empty folder beside ``target`` to fill; on success it replaces ``target`` (an
    existing one is removed), on any exception (Ctrl-C included) it is removed and ``target`` is
    left as it was."""
    partial = temporary_sibling(check_target(target, folder=True))
    partial.mkdir()
    try:
        yield partial
        replace_folder(partial, target)
    finally:
        shutil.rmtree(partial, ignore_errors=True)
