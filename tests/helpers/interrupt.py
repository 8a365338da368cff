"""Child processes that a test interrupts as a terminal's Ctrl-C does."""

from __future__ import annotations

import signal
import subprocess
from collections.abc import Sequence
from typing import Any


def interruptible(args: Sequence[str], **popen: Any) -> subprocess.Popen:
    """``subprocess.Popen(args, **popen)`` with SIGINT raising KeyboardInterrupt in the child, whatever
    this process inherited. A shell starts a background job with SIGINT ignored and an ignored signal
    stays ignored across exec, so a child of a suite run that way would never see the test's SIGINT; a
    handled one is reset to the default at exec, which Python turns into KeyboardInterrupt. Call from
    the main thread (the only one that may set a handler)."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        return subprocess.Popen(args, **popen)
    finally:
        signal.signal(signal.SIGINT, previous)
