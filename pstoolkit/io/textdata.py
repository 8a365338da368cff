"""Reading the JSON and TOML files users hand the toolkit (result.json, settings files), bounded.

Such a file may be crafted: it is read only when it is a regular file of at most ``MAX_TEXT_BYTES``
(checked before reading, so a sparse file of gigabytes costs nothing), decoded as UTF-8, parsed, and
accepted only when it nests at most ``MAX_DEPTH`` arrays and tables deep and holds no integer outside
``INT_RANGE`` (a 400-digit integer would overflow the first ``float()`` that meets it, a seed of 2⁶⁴ torch). Every refusal is
a UserError naming the file. Every reader of result.json and of settings files goes through here.
"""

from __future__ import annotations

import json
import os
import stat
import sys
from pathlib import Path
from typing import Any

import numpy as np

from psfmt.text import printable
from pstoolkit._shared.numbers import INT_RANGE
from pstoolkit.errors import UserError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10 has no tomllib; tomli is the same parser (a dependency there)
    import tomli as tomllib

MAX_TEXT_BYTES = 16 << 20
"""Largest JSON or TOML file read (16 MiB): a result.json of a 4096² run is a few kilobytes."""
MAX_DEPTH = 64
"""Deepest nesting of arrays and tables accepted (the toolkit writes at most 4)."""
_MAX_INT_DIGITS = 19


def read_text(path: Path) -> str:
    """The UTF-8 text of the regular file ``path`` of at most ``MAX_TEXT_BYTES``; UserError otherwise.
    Opened without blocking, so a FIFO under the name is refused instead of waited on."""
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except FileNotFoundError:
        raise UserError(f"{path}: no such file") from None
    except OSError as exc:
        raise UserError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    with open(fd, "rb") as fh:
        info = os.fstat(fh.fileno())
        if not stat.S_ISREG(info.st_mode):
            raise UserError(f"{path}: not a regular file")
        if info.st_size > MAX_TEXT_BYTES:
            raise UserError(f"{path}: {info.st_size} bytes, over the {MAX_TEXT_BYTES} bytes a JSON or TOML file may have")
        data = fh.read(MAX_TEXT_BYTES + 1)
    if len(data) > MAX_TEXT_BYTES:  # grew while being read
        raise UserError(f"{path}: over the {MAX_TEXT_BYTES} bytes a JSON or TOML file may have")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise UserError(f"{path}: not UTF-8 text (byte {exc.start})") from None


def _bounded_int(text: str) -> int:
    if len(text.lstrip("-")) > _MAX_INT_DIGITS:
        raise ValueError(f"an integer of {len(text.lstrip('-'))} digits")
    return int(text)


def check_value(value: Any, path: Path) -> Any:
    """``value`` (parsed JSON or TOML) when it nests at most ``MAX_DEPTH`` deep and every integer
    lies in ``INT_RANGE``; UserError naming ``path`` otherwise. Iterative: a deep value cannot
    exhaust the stack here."""
    pending: list[tuple[Any, int]] = [(value, 0)]
    while pending:
        item, depth = pending.pop()
        if isinstance(item, dict):
            children: Any = item.values()
        elif isinstance(item, list):
            children = item
        else:
            if isinstance(item, int) and not isinstance(item, bool) and not INT_RANGE[0] <= item <= INT_RANGE[1]:
                raise UserError(f"{path}: an integer outside the 64-bit range ({len(str(abs(item)))} digits)")
            continue
        if depth >= MAX_DEPTH:
            raise UserError(f"{path}: nested more than {MAX_DEPTH} levels deep")
        pending.extend((child, depth + 1) for child in children)
    return value


def read_json(path: Path) -> Any:
    """The JSON value in ``path`` (``read_text``'s bounds, ``check_value``'s); UserError naming the
    file for anything else, invalid JSON and nesting deeper than the parser can follow included."""
    text = read_text(path)
    try:
        value = json.loads(text, parse_int=_bounded_int)
    except RecursionError:
        raise UserError(f"{path}: not valid JSON (nested more than {MAX_DEPTH} levels deep)") from None
    except json.JSONDecodeError as exc:
        raise UserError(f"{path}: not valid JSON ({exc.msg} at line {exc.lineno})") from None
    except ValueError as exc:  # _bounded_int's
        raise UserError(f"{path}: not valid JSON ({printable(exc)})") from None
    return check_value(value, path)


def read_json_object(path: Path) -> dict[str, Any]:
    """``read_json`` for a file that must hold a JSON object."""
    value = read_json(path)
    if not isinstance(value, dict):
        raise UserError(f"{path}: expected a JSON object")
    return value


def read_toml(path: Path) -> dict[str, Any]:
    """The TOML table in ``path``, with ``read_json``'s bounds."""
    text = read_text(path)
    try:
        value = tomllib.loads(text)
    except RecursionError:
        raise UserError(f"{path}: not a valid TOML file (nested more than {MAX_DEPTH} levels deep)") from None
    except ValueError as exc:  # TOMLDecodeError, and the integer-digits limit of int()
        raise UserError(f"{path}: not a valid TOML file ({printable(exc)})") from None
    return check_value(value, path)


def _jsonable(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    return str(value)


def summary_json(summary: dict[str, Any]) -> str:
    """``result.json``'s text (numpy values as plain numbers, anything else unknown as a string)."""
    return json.dumps(summary, indent=2, default=_jsonable)
