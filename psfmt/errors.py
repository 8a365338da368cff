"""The one exception type of psfmt: a file that is not a usable hybrid capture."""

from __future__ import annotations

from os import PathLike


class FormatError(ValueError):
    """A file cannot be read or written as a hybrid capture.

    ``str(error)`` is one line naming the file and the problem, fit to show a user as is.
    """

    def __init__(self, path: str | PathLike[str], message: str) -> None:
        self.path = str(path)
        self.message = message
        super().__init__(f"{self.path}: {message}")
