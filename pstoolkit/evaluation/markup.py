"""Untrusted strings in the markdown and HTML the toolkit writes.

Names of objects and results, and error lines, come from files anyone may have made. In a markdown
page a ``|`` shifts a table cell, a newline starts a heading, ``[x](javascript:…)`` is a link and raw
HTML (``<img src=x onerror=…>``, ``<script>``) passes through most renderers; ``md`` turns such a
string into markdown that shows it literally, whether the page is read as markdown or turned into
HTML by ``pstoolkit.evaluation.report``.
"""

from __future__ import annotations

import html
import re

from psfmt.text import printable

_SPECIAL = re.compile(r"([\\`*_\[\](){}#|~!])")
"""Punctuation that makes markdown syntax anywhere in a line."""
_LEADING = re.compile(r"^([-+=]|\d+(?=[.)]))")
"""What makes a list item or a heading underline only at the start of a line: escaped there."""
ESCAPE = re.compile(r"\\([!-/:-@\[-`{-~])")
"""A backslash escape of CommonMark (any ASCII punctuation): what a reader of ``md`` output undoes."""


def md(text: object) -> str:
    """``text`` as one line of markdown that renders as exactly that text: control characters
    stripped and line breaks made spaces (``psfmt.text.printable``), ``&``, ``<`` and ``>`` as HTML
    entities (so no renderer sees a tag), markdown punctuation backslash-escaped (CommonMark §2.4)."""
    escaped = _SPECIAL.sub(r"\\\1", html.escape(printable(text), quote=False))
    leading = _LEADING.match(escaped)
    if leading is None:
        return escaped
    if leading[1][0].isdigit():  # "1. x" would start an ordered list: escape its dot or parenthesis
        end = leading.end()
        return f"{escaped[:end]}\\{escaped[end:]}"
    return "\\" + escaped
