"""Typed options of registry entries, and parsing of ``--set key=value`` against them."""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

from pstoolkit.errors import UserError

_TRUE = {"1", "true", "yes", "on"}
_FALSE = {"0", "false", "no", "off"}


@dataclass(frozen=True)
class Option:
    """One option of a solver, scene, backend …: ``type`` is int, float, bool or str; ``choices``
    restricts a str option; ``minimum``/``maximum`` bound a number. A float option is finite: NaN
    passes no range check and is not JSON, infinity is no setting. A ``multiple`` option may be
    given repeatedly: its value is the tuple of the given values in order (``default`` when none).
    A ``nested`` option (a multiple str) collects the options of another registry entry the owner
    uses (a solver's shadow detector): ``--set NAME.key=value`` adds ``"key=value"`` to it."""

    name: str
    type: type
    default: Any
    help: str
    choices: tuple[str, ...] | None = None
    minimum: float | None = None
    maximum: float | None = None
    multiple: bool = False
    nested: bool = False

    def parse(self, text: str) -> Any:
        """Convert a command-line string, raising UserError with the option's name on bad input."""
        if self.type is bool:
            low = text.strip().lower()
            if low in _TRUE:
                return True
            if low in _FALSE:
                return False
            raise UserError(f"option {self.name}: expected true or false, got {text!r}")
        try:
            value = self.type(text)
        except ValueError:
            raise UserError(f"option {self.name}: expected {self.type.__name__}, got {text!r}") from None
        return self.check(value)

    def check(self, value: Any) -> Any:
        if self.type is float and not math.isfinite(value):
            raise UserError(f"option {self.name}: {value!r} is not a finite number")
        if self.choices is not None and value not in self.choices:
            raise UserError(f"option {self.name}: {value!r} is not one of {', '.join(self.choices)}")
        if self.minimum is not None and value < self.minimum:
            raise UserError(f"option {self.name}: {value!r} is below the minimum {self.minimum:g}")
        if self.maximum is not None and value > self.maximum:
            raise UserError(f"option {self.name}: {value!r} is above the maximum {self.maximum:g}")
        return value

    def describe(self) -> str:
        extra = f"; one of {', '.join(self.choices)}" if self.choices else ""
        if self.nested:
            return f"{self.name}.KEY=VALUE: {self.help}"
        extra += "; repeatable" if self.multiple else ""
        return f"{self.name} ({self.type.__name__}, default {self.default!r}{extra}): {self.help}"


def defaults(options: Iterable[Option]) -> dict[str, Any]:
    return {o.name: o.default for o in options}


def parse_assignments(pairs: Sequence[str], options: Sequence[Option], owner: str) -> dict[str, Any]:
    """``["frames=6", "robust=true"]`` → the full option dict (defaults filled in) for ``owner``;
    unknown keys and bad values raise UserError naming the key and the known ones."""
    known = {o.name: o for o in options}
    values = defaults(options)
    given: set[str] = set()
    for pair in pairs:
        key, sep, text = pair.partition("=")
        key = key.strip()
        if not sep or not key:
            raise UserError(f"--set {pair!r}: expected key=value")
        head, dot, inner = key.partition(".")
        if dot and head in known and known[head].nested:
            if not inner:
                raise UserError(f"--set {pair!r}: expected {head}.key=value")
            key, text = head, f"{inner}={text}"
        elif key in known and known[key].nested:
            raise UserError(f"--set {pair!r}: give {key}'s options as {key}.key=value")
        if key not in known:
            names = ", ".join(sorted(known)) or "none"
            raise UserError(f"{owner} has no option {key!r} (options: {names})")
        option = known[key]
        value = option.parse(text)
        if option.multiple:
            # the first assignment replaces the default, later ones add to it
            value = (*(values[key] if key in given else ()), value)
        values[key] = value
        given.add(key)
    return values
