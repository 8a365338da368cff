"""User-facing errors: one line, no traceback, exit code 2 from the CLI."""

from __future__ import annotations


class UserError(Exception):
    """Bad input from a user (a missing file, a wrong option); ``str`` is the line to show."""
