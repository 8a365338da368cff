"""Strings taken from files, made safe to show: without the characters that drive a terminal.

A capture's description, a result's name or a JSON field may hold escape sequences (``ESC]0;…BEL``
sets a window title, ``ESC[2J`` clears the screen), carriage returns and backspaces that overwrite
what was printed, or Unicode direction overrides that show text in another order than it is stored.
``printable`` removes them all; every string a program prints from a file goes through it.
"""

from __future__ import annotations

import re

# C0 and C1 controls and DEL (tab, newline and carriage return are handled apart), the bidirectional
# marks, embeddings, overrides and isolates, and lone surrogates (undecodable bytes)
_CONTROLS = re.compile("[\x00-\x08\x0b\x0c\x0e-\x1f\x7f-\x9f\u061c\u200e\u200f\u202a-\u202e\u2066-\u2069\ud800-\udfff]")
_BREAKS = re.compile("\r\n|[\t\n\r]")


def printable(text: object, *, newlines: bool = False) -> str:
    """``str(text)`` without control characters. Tabs, carriage returns and newlines become spaces,
    so the result is one line, unless ``newlines`` keeps line breaks (as ``\\n``)."""
    s = _CONTROLS.sub("", str(text))
    if newlines:
        return _BREAKS.sub(lambda m: " " if m[0] == "\t" else "\n", s)
    return _BREAKS.sub(" ", s)
