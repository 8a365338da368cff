"""User-facing errors: one line, no traceback, exit code 2 from the CLI."""

from __future__ import annotations


class UserError(Exception):
    """Bad input from a user (a missing file, a wrong option); ``str`` is the line to show."""


class Interrupted(Exception):
    """Raised by a command that has cleaned up after a Ctrl-C, saying what it left behind (``str``:
    "the lights are off …"); the CLI prints "interrupted: " and that, and exits with 130."""
