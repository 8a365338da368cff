"""What a check reports: one ``Finding`` per problem, collected in ``Findings``."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class Finding:
    """One problem: ``level`` is ``error`` or ``warning``; ``where`` the HDF5 path it concerns."""

    level: str
    where: str
    message: str
    fatal: bool = False

    @property
    def text(self) -> str:
        return f"{self.where}: {self.message}"


class Findings(list[Finding]):
    """The findings of one pass of checks, in the order they were found."""

    def error(self, where: str, message: str) -> None:
        self.append(Finding("error", where, message))

    def warn(self, where: str, message: str) -> None:
        self.append(Finding("warning", where, message))

    def fatal(self, where: str, message: str) -> None:
        """The file is not a readable capture at all: nothing else is worth checking."""
        self.append(Finding("error", where, message, fatal=True))

    @property
    def failed(self) -> bool:
        return any(x.level == "error" for x in self)
