"""The converter interface: what ``pstoolkit convert NAME SRC -o OUT`` calls.

A converter is a ``Converter`` subclass registered through ``pstoolkit_register_converters``:

    class MyDataset(Converter):
        name = "mydataset"
        summary = "folders of my lab's PNG captures"
        options = (Option("size", int, 0, "resize to N×N (0: keep)", minimum=0),)

        def convert(self, src, out, options, progress):
            ...  # read and check everything in src first, then write through psfmt.CaptureWriter
            return [out]

Converter options come from the command line as flags (``--size 128``, a bool option as a bare
``--flag``, a ``multiple`` option repeated) or as ``--set key=value``.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from pathlib import Path
from typing import Any, ClassVar

from psfmt.atomic import check_target
from pstoolkit._shared.progress import Progress, no_progress
from pstoolkit.errors import UserError
from pstoolkit.plugin.options import Option
from pstoolkit.plugin.registry import Entry, PluginError


class Converter(ABC):
    """Base of converters: ``name`` (registry name, the NAME of ``pstoolkit convert``), ``summary``
    (one line) and typed ``options``."""

    name: ClassVar[str]
    summary: ClassVar[str]
    options: ClassVar[tuple[Option, ...]] = ()

    @abstractmethod
    def convert(self, src: Path, out: Path, options: dict[str, Any], progress: Progress) -> list[Path]:
        """Convert ``src`` into capture file(s) at ``out`` with the full ``options`` dict (defaults
        filled in) and return the paths written. Bad input is a UserError raised before anything is
        written; writes are atomic."""


def run_converter(
    entry: Entry, src: Path, out: Path, options: dict[str, Any], progress: Progress = no_progress
) -> list[Path]:
    """Run the registered converter ``entry``; a missing SRC is a UserError, an entry that is not a
    ``Converter`` or a converter that returns something other than a list of paths is a PluginError."""
    blame = f"plugin {entry.plugin!r}: converter {entry.name!r}"
    if not (isinstance(entry.obj, type) and issubclass(entry.obj, Converter)):
        raise PluginError(f"{blame} is not a pstoolkit.io.converter.Converter subclass")
    if not src.exists():
        raise UserError(f"{src}: does not exist")
    # a folder OUT receives new files (each written through the same rule), a file OUT is replaced
    into = out.is_dir() and not out.is_symlink()
    check_target(out, [] if into else [src], folder=into)
    written = entry.obj().convert(src, out, options, progress)
    if not isinstance(written, list) or not all(isinstance(p, Path) for p in written):
        raise PluginError(f"{blame} returned {type(written).__name__}, expected a list of paths")
    return written
