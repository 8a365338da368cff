"""Command line: ``pstoolkit COMMAND``. Each command lives in its own module and registers on the app.

The command modules are imported when ``main`` first runs, not when this package is, and a Ctrl-C
during those imports ends in one line like a Ctrl-C anywhere else, not in a traceback. A command
module imports only what its options and help need (typer, psfmt, the registries): torch, numba,
matplotlib, OpenCV, scipy and dask load inside the command bodies that use them, so that
``pstoolkit --help`` and ``pstoolkit info`` start in a fraction of a second
(``tests/cli/test_cli_polish.py`` checks the modules ``--help`` and ``info`` load).
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
