"""``pstoolkit convert NAME SRC -o OUT [converter options]``: turn a dataset into hybrid capture(s).

The converter's typed options are given as flags built from their names (option ``discrete_lights``
is ``--discrete-lights K``; a bool option is a bare ``--flag`` or ``--no-flag``; a ``multiple``
option is repeated) or as ``--set key=value``; the flags are parsed generically against the
converter's registry entry, so a plugin's converter gets its command line for free.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import typer

from pstoolkit.cli.app import app, echo, progress_bar
from pstoolkit.errors import UserError
from pstoolkit.io.converter import run_converter
from pstoolkit.plugin.manager import get_registries
from pstoolkit.plugin.options import Option
from pstoolkit.plugin.registry import Entry

HELP_FLAGS = ("-h", "--help")


def flag_name(option: Option) -> str:
    return "--" + option.name.replace("_", "-")


def flag_assignments(tokens: Sequence[str], options: Sequence[Option], owner: str) -> tuple[list[str], list[str]]:
    """Split command-line tokens into ``key=value`` assignments of ``options`` and positional
    arguments. ``--flag VALUE`` and ``--flag=VALUE`` set a value, a bare ``--flag`` / ``--no-flag``
    sets a bool option; an unknown flag raises UserError listing the flags of ``owner``."""
    by_flag = {flag_name(o): o for o in options}
    pairs: list[str] = []
    positional: list[str] = []
    tokens = list(tokens)
    i = 0
    while i < len(tokens):
        token = tokens[i]
        i += 1
        if not token.startswith("-") or token == "-":
            positional.append(token)
            continue
        flag, sep, text = token.partition("=")
        option = by_flag.get(flag)
        negated = by_flag.get("--" + flag[len("--no-") :]) if option is None and flag.startswith("--no-") else None
        if negated is not None and negated.type is bool and not sep:
            pairs.append(f"{negated.name}=false")
            continue
        if option is None:
            known = ", ".join(sorted(by_flag)) or "none"
            raise UserError(f"{owner} has no option {flag} (options: {known}; see `pstoolkit convert NAME --help`)")
        if not sep:
            if option.type is bool:
                text = "true"
            elif i < len(tokens):
                text = tokens[i]
                i += 1
            else:
                raise UserError(f"{flag} needs a value ({option.type.__name__})")
        pairs.append(f"{option.name}={text}")
    return pairs, positional


def _shown(value: object) -> str:
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, tuple):
        return " ".join(map(str, value)) or "none"
    return repr(value)


def converter_help(entry: Entry) -> str:
    """The usage and option list of one converter."""
    lines = [
        f"Usage: pstoolkit convert {entry.name} SRC -o OUT [OPTIONS]",
        "",
        f"  {entry.summary}  (plugin {entry.plugin})",
        "",
        "Options (as --flag VALUE, or --set key=value):",
    ]
    for option in entry.options:
        kind = "flag" if option.type is bool else option.type.__name__.upper()
        if option.multiple:
            kind += ", repeatable"
        lines.append(f"  {flag_name(option)} ({kind}, default {_shown(option.default)}): {option.help}")
    if not entry.options:
        lines.append("  (none)")
    return "\n".join(lines)


def _listing(ctx: typer.Context) -> str:
    entries = get_registries().converters.entries()
    width = max((len(e.name) for e in entries), default=0)
    rows = [f"  {e.name:<{width}}  {e.summary}" for e in entries] or ["  (none registered)"]
    return "\n".join([ctx.get_help(), "", "Converters (options: pstoolkit convert NAME --help):", *rows])


@app.command(
    "convert",
    context_settings={"ignore_unknown_options": True, "allow_extra_args": True, "help_option_names": []},
)
def convert(
    ctx: typer.Context,
    args: list[str] = typer.Argument(None, metavar="NAME SRC [CONVERTER OPTIONS]", show_default=False),
    out: Path | None = typer.Option(None, "-o", "--out", help="Capture file to write; a folder when several objects are converted (always with --all)."),
    assignments: list[str] = typer.Option([], "--set", metavar="KEY=VALUE", help="A converter option; repeat for more."),
    as_json: bool = typer.Option(False, "--json", help="Print the files written as JSON and no progress."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar and no summary."),
) -> None:
    """Convert a dataset (DiLiGenT, DiLiGenT-Π or a plugin's format) into hybrid capture(s). NAME is a
    registered converter; each converter's own options (e.g. --semi-real, --object NAME) are listed
    by `pstoolkit convert NAME --help`."""
    tokens = list(args or []) + list(ctx.args)
    helping = any(t in HELP_FLAGS for t in tokens)
    tokens = [t for t in tokens if t not in HELP_FLAGS]
    if not tokens or tokens[0].startswith("-"):
        if helping or not tokens:
            echo(_listing(ctx))
            return
        raise UserError(f"expected a converter NAME before {tokens[0]} (pstoolkit convert NAME SRC -o OUT)")
    entry = get_registries().converters.get(tokens[0])
    if helping:
        echo(converter_help(entry))
        return
    pairs, positional = flag_assignments(tokens[1:], entry.options, f"converter {entry.name!r}")
    if len(positional) != 1:
        found = f"got {' '.join(positional)}" if positional else "got none"
        raise UserError(f"convert {entry.name}: expected one SRC (a file or folder), {found}")
    options = entry.parse_options([*assignments, *pairs])
    if out is None:
        raise UserError(f"convert {entry.name}: give the output with -o OUT")
    progress = progress_bar(f"convert {entry.name}", quiet or as_json)
    written = run_converter(entry, Path(positional[0]), out, options, progress)
    if as_json:
        echo(json.dumps({"converter": entry.name, "written": [str(path) for path in written]}, indent=2))
    elif not quiet:
        for path in written:
            echo(f"wrote {path}")
