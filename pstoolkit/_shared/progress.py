"""How long work reports how far it is: the callback every solver, converter, simulator and exporter takes."""

from __future__ import annotations

from collections.abc import Callable

Progress = Callable[[float, str], None]
"""``progress(fraction, message)``: fraction of the work done in [0, 1] and what is happening."""


def no_progress(fraction: float, message: str) -> None:
    """The progress callback that reports nowhere."""
