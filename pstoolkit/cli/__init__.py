"""Command line: ``pstoolkit COMMAND``. Each command lives in its own module and registers on ``app``."""

from __future__ import annotations

from pstoolkit.cli import batch, calibrate, capture, convert, eval, export, info, plugins, report, run, simulate, validate  # noqa: F401  (registers the commands)
from pstoolkit.cli.app import app, main
from pstoolkit.plugins import add_commands

add_commands(app)

__all__ = ["app", "main"]
