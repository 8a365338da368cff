"""Typed options of registry entries, parsing of ``--set key=value`` against them, and the typed
values of a settings file (TOML or JSON) turned into the same ``key=value`` strings."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from pstoolkit._shared.numbers import INT_RANGE
from pstoolkit.errors import UserError

_TRUE = {"1", "true", "yes", "on"}
_FALSE = {"0", "false", "no", "off"}


@dataclass(frozen=True)
class Option:
    """One option of a solver, scene, backend …: ``type`` is int, float, bool or str; ``choices``
    restricts a str option; ``minimum``/``maximum`` bound a number; an int lies in int64 (``_shared.numbers.INT_RANGE``). A float option is finite: NaN
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
        if self.type is int and not INT_RANGE[0] <= value <= INT_RANGE[1]:  # beyond what torch or numba takes
            shown = value if len(str(value)) <= 24 else f"an integer of {len(str(abs(value)))} digits"
            raise UserError(f"option {self.name}: {shown} is outside the 64-bit integers")
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


def fill_defaults(values: Mapping[str, Any], options: Sequence[Option], owner: str) -> dict[str, Any]:
    """A partial option dict (``{"robust": True}``) → the full one, each option left out at its
    default. Values are taken as given (a typed caller's, or ``parse_assignments``'s); an unknown key
    raises the UserError ``--set`` raises for it."""
    known = {o.name for o in options}
    unknown = sorted(set(values) - known)
    if unknown:
        names = ", ".join(sorted(known)) or "none"
        raise UserError(f"{owner} has no option {unknown[0]!r} (options: {names})")
    return {**defaults(options), **values}


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


def value_kind(value: Any) -> str:
    """What a TOML or JSON value is, in words, for an error message."""
    if isinstance(value, bool):
        return "a boolean"
    if isinstance(value, int):
        return "an integer"
    if isinstance(value, float):
        return "a number"
    if isinstance(value, str):
        return "a string"
    if isinstance(value, list):
        return "an array"
    if isinstance(value, dict):
        return "a table"
    return f"a {type(value).__name__}"


_EXPECTED = {bool: "true or false", int: "an integer", float: "a number", str: "a string"}


def format_value(value: Any) -> str:
    """The ``--set`` text of one typed value that ``Option.parse`` reads back as the same value
    (floats through ``repr``, which round-trips exactly; bools as true/false)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value)
    return str(value)


def format_assignments(values: dict[str, Any], options: Sequence[Option]) -> list[str]:
    """The inverse of ``parse_assignments``: ``key=value`` strings that parse back to ``values``
    (a full option dict); a multiple option gives one string per value (none for an empty tuple,
    which then parses back to the default only when that is empty too), a nested one ``NAME.key=value``."""
    pairs: list[str] = []
    for option in options:
        value = values[option.name]
        if option.nested:
            pairs += [f"{option.name}.{inner}" for inner in value]
        elif option.multiple:
            pairs += [f"{option.name}={format_value(v)}" for v in value]
        else:
            pairs.append(f"{option.name}={format_value(value)}")
    return pairs


def _typed(option: Option, value: Any, where: str) -> Any:
    """``value`` from a settings file checked against ``option``'s type (an integer is a number too,
    nothing else converts: ``"6"`` is not an integer and ``1`` not a boolean) and bounds."""
    wanted = option.type
    ok = isinstance(value, wanted) and not (wanted is int and isinstance(value, bool))
    if wanted is float and isinstance(value, int) and not isinstance(value, bool):
        value, ok = float(value), True
    if not ok:
        expected = _EXPECTED.get(wanted, wanted.__name__)
        raise UserError(f"{where}: expected {expected}, got {value_kind(value)} {value!r}")
    try:
        return option.check(value)
    except UserError as exc:
        # where names the key already
        raise UserError(f"{where}: {str(exc).removeprefix(f'option {option.name}: ')}") from None


def table_assignments(table: dict[str, Any], options: Sequence[Option], owner: str, where: str) -> list[str]:
    """The typed values of a settings-file table (TOML ``[options]``, a result.json's ``options``) →
    ``key=value`` strings for ``parse_assignments``, each checked first so that an error names the
    file and the key: ``where`` prefixes the key (``"run.toml: options"`` → ``"run.toml:
    options.frames: expected an integer, got a string '6'"``).

    A multiple option takes an array of values (or one value); a nested option a table of its owner's
    settings (``[options.shadow]``, values of any type, checked when the nested entry parses them) or
    an array of ``"key=value"`` strings (as result.json records it). UserError for an unknown key, a
    value of the wrong type or out of bounds."""
    known = {o.name: o for o in options}
    pairs: list[str] = []
    for key, value in table.items():
        at = f"{where}.{key}"
        option = known.get(key)
        if option is None:
            names = ", ".join(sorted(known)) or "none"
            raise UserError(f"{at}: {owner} has no option {key!r} (options: {names})")
        if option.nested:
            if isinstance(value, dict):
                for inner, setting in value.items():
                    if isinstance(setting, (dict, list)):
                        raise UserError(f"{at}.{inner}: expected a single value, got {value_kind(setting)}")
                    pairs.append(f"{key}.{inner}={format_value(setting)}")
            elif isinstance(value, list) and all(isinstance(v, str) and "=" in v for v in value):
                pairs += [f"{key}.{inner}" for inner in value]
            else:
                raise UserError(f"{at}: expected a table of {key}'s options (or an array of \"key=value\" strings), got {value_kind(value)}")
        elif option.multiple:
            for item in value if isinstance(value, list) else [value]:
                pairs.append(f"{key}={format_value(_typed(option, item, at))}")
        else:
            pairs.append(f"{key}={format_value(_typed(option, value, at))}")
    return pairs
