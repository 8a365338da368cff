"""Command line: ``pstoolkit COMMAND``. Each command lives in its own module and registers on the app.

The command modules are imported when ``main`` first runs, not when this package is: they bring in
torch, numba and matplotlib (seconds of imports), and a Ctrl-C during those ends in one line like a
Ctrl-C anywhere else, not in a traceback.
"""

from __future__ import annotations

import sys
from collections.abc import Callable

_main: list[Callable[[list[str] | None], int]] = []


def _commands() -> Callable[[list[str] | None], int]:
    """Import every command (each registers itself) and the plugins' commands, once; the app's main."""
    if not _main:
        from pstoolkit.cli import batch, calibrate, capture, convert, evaluate, export, info, integrate, plugins, report, run, simulate, validate, view  # noqa: F401
        from pstoolkit.cli.app import app
        from pstoolkit.cli.app import main as app_main
        from pstoolkit.plugin.manager import add_commands

        add_commands(app)
        _main.append(app_main)
    return _main[0]


def main(argv: list[str] | None = None) -> int:
    """Console entry point (see ``pstoolkit.cli.app.main`` for the exit codes)."""
    try:
        app_main = _commands()
    except KeyboardInterrupt:
        sys.stderr.write("pstoolkit: error: interrupted\n")
        if argv is None:
            sys.exit(130)
        return 130
    return app_main(argv)


__all__ = ["main"]
