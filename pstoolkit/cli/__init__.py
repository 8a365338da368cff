"""Command line: ``pstoolkit COMMAND``. Each command lives in its own module and registers on ``app``."""

from __future__ import annotations

from pstoolkit.cli import info, validate  # noqa: F401  (registers the commands)
from pstoolkit.cli.app import app, main

__all__ = ["app", "main"]
