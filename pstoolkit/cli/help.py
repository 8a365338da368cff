"""Plain ``--help`` pages: ``SCENE``, ``--size INTEGER``, ``--set KEY=VALUE``, ``[default: 33.3333]``.

Typer writes a required argument as ``{scene}`` in the usage line and appends a type label such as
``<list[str]>`` or ``<path>`` to every parameter, even one given a metavar; those are its internals,
not words for the reader. ``PlainCommand`` and ``PlainGroup`` write the usage line and the
parameter list themselves: a parameter's ``metavar`` when it has one, else an argument's name in
capitals and an option's value type as click names it (``INTEGER``, ``FLOAT``, ``TEXT``, ``PATH``);
a float default is shown to six significant digits when its repr is longer (a period of 1000/30 ms
reads 33.3333, not 33.333333333333336). Everything else (sections, wrapping) is click's formatter.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, get_args, get_origin

from typer.core import TyperCommand, TyperGroup

_LONG_NUMBER = 8
"""A float default whose repr is longer than this is shown to six significant digits."""


_TYPE_NAMES = {int: "INTEGER", float: "FLOAT", str: "TEXT", bool: "BOOLEAN", Path: "PATH"}


def value_name(param: Any) -> str:
    """An option's value type as click names it: ``INTEGER``, ``FLOAT``, ``TEXT``, ``PATH``, the
    choices as ``a|b``; the element type of a list (a repeatable option takes one value at a time)."""
    descriptor = getattr(param, "type_descriptor", None)
    if descriptor is None:  # a plain click parameter (a plugin's own command class)
        return str(getattr(getattr(param, "type", None), "name", "value")).upper()
    if descriptor.is_choice:
        return "|".join(str(getattr(c, "value", c)) for c in descriptor.choices or ())
    if descriptor.is_path:
        return "PATH"
    annotation = descriptor.annotation
    if get_origin(annotation) in (list, tuple) and get_args(annotation):
        annotation = get_args(annotation)[0]
    return _TYPE_NAMES.get(annotation, str(getattr(annotation, "__name__", "value")).upper())


def metavar(param: Any) -> str:
    """What stands for the parameter's value: its ``metavar``, else an argument's name in capitals,
    else the option's value type (``value_name``)."""
    if param.metavar:
        return str(param.metavar)
    if param.param_type_name == "argument":
        return str(param.name).upper()
    return value_name(param)


def _shown(value: Any) -> str:
    if isinstance(value, float):
        text = repr(value)
        return text if len(text) <= _LONG_NUMBER else f"{value:.6g}"
    return str(value)


def default_text(param: Any, ctx: Any) -> str | None:
    """The default to show in brackets, or None: a ``show_default`` string as given; nothing for no
    default, an empty list or an unset flag; the on/off name of a ``--x/--no-x`` flag."""
    show = getattr(param, "show_default", True)
    if isinstance(show, str):
        return show
    if not show:
        return None
    resilient = ctx.resilient_parsing
    ctx.resilient_parsing = True  # the default as declared, not converted (a converter could fail)
    try:
        value = param.get_default(ctx, call=False)
    finally:
        ctx.resilient_parsing = resilient
    if value is None or callable(value) or (isinstance(value, (list, tuple)) and not value):
        return None
    if getattr(param, "is_bool_flag", False):
        if param.secondary_opts:
            return (param.opts[0] if value else param.secondary_opts[0]).lstrip("-")
        return None  # a bare flag: off unless given; its help says what it does
    if isinstance(value, (list, tuple)):
        return ", ".join(_shown(v) for v in value)
    return _shown(value)


def help_record(param: Any, ctx: Any) -> tuple[str, str] | None:
    """(left column, help) of one parameter, or None for a hidden one."""
    if getattr(param, "hidden", False):
        return None
    if param.param_type_name == "argument":
        name = metavar(param) + ("..." if param.nargs != 1 and not param.metavar else "")
    else:
        takes_value = not getattr(param, "is_flag", False) and not getattr(param, "count", False)
        sides = [", ".join(sorted(param.opts, key=lambda o: len(o) - len(o.lstrip("-"))))]
        if param.secondary_opts:
            sides.append(", ".join(param.secondary_opts))
        name = " / ".join(sides) + (f" {metavar(param)}" if takes_value else "")
    extra = []
    default = default_text(param, ctx)
    if default:
        extra.append(f"default: {default}")
    if param.required:
        extra.append("required")
    help_text = getattr(param, "help", None) or ""
    if extra:
        help_text = f"{help_text}  [{'; '.join(extra)}]" if help_text else f"[{'; '.join(extra)}]"
    return name, help_text


def usage_pieces(command: Any, ctx: Any) -> list[str]:
    """``[OPTIONS]`` and the arguments: ``NAME`` when required, ``[NAME]`` when not, ``...`` after
    one that takes several values; an argument's own metavar is used as written."""
    pieces = [command.options_metavar] if command.options_metavar else []
    for param in command.get_params(ctx):
        if param.param_type_name != "argument":
            continue
        if param.metavar:
            pieces.append(str(param.metavar))
            continue
        piece = metavar(param) + ("..." if param.nargs != 1 else "")
        pieces.append(piece if param.required else f"[{piece}]")
    return pieces


def format_parameters(command: Any, ctx: Any, formatter: Any) -> None:
    """The Arguments and Options sections of a help page."""
    records: dict[str, list[tuple[str, str]]] = {"argument": [], "option": []}
    for param in command.get_params(ctx):
        record = help_record(param, ctx)
        if record is not None and param.param_type_name in records:
            records[param.param_type_name].append(record)
    for title, kind in (("Arguments", "argument"), ("Options", "option")):
        if records[kind]:
            with formatter.section(title):
                formatter.write_dl(records[kind])


class PlainCommand(TyperCommand):
    """A typer command whose help names values plainly (see the module)."""

    def collect_usage_pieces(self, ctx: Any) -> list[str]:
        return usage_pieces(self, ctx)

    def format_options(self, ctx: Any, formatter: Any) -> None:
        format_parameters(self, ctx, formatter)


class PlainGroup(TyperGroup):
    """The top-level group, with its options written as ``PlainCommand`` writes them."""

    def collect_usage_pieces(self, ctx: Any) -> list[str]:
        return [*usage_pieces(self, ctx), self.subcommand_metavar]

    def format_options(self, ctx: Any, formatter: Any) -> None:
        format_parameters(self, ctx, formatter)
        self.format_commands(ctx, formatter)
