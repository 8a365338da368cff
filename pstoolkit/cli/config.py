"""``--config FILE`` of ``pstoolkit run`` and ``pstoolkit batch``: the settings file
(``pstoolkit.solve.config``, ``docs/config.md``) wired into the command line.

The option is eager: its callback reads FILE before the other parameters are taken and hands the
file's flag values to the command as its defaults (the context's ``default_map``, click's mechanism
for configuration files), so a flag given on the command line overrides the file's value and a flag
required there (``--solver``) may come from the file instead. The file itself is kept in the context
for the command's body: its solver options go before those of ``--set`` (the later assignment of a
key wins), and a result.json's capture is checked by its checksum when it is the one the run reads.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import typer

from pstoolkit.cli.app import echo
from pstoolkit.plugin.registry import Entry
from pstoolkit.solve.config import CommandConfig, read_config

_META_KEY = "pstoolkit.config"


def _callback(command: str) -> Callable[[Any, Any, Path | None], Path | None]:
    def load(ctx: Any, param: Any, value: Path | None) -> Path | None:
        if value is None:
            return None
        config = read_config(value, command)
        ctx.default_map = {**(ctx.default_map or {}), **config.flags}
        ctx.meta[_META_KEY] = config
        return value

    return load


def config_option(command: str) -> Any:
    """The ``--config FILE`` option of ``command`` (``run`` or ``batch``), for its signature."""
    extra = " or the result.json of an earlier run, to repeat it (its capture must be unchanged)" if command == "run" else ""
    return typer.Option(
        None, "--config", is_eager=True, callback=_callback(command), metavar="FILE",
        help=f"Settings from a TOML file (docs/config.md){extra}; flags given here override the file's.",
    )


def loaded(ctx: Any) -> CommandConfig | None:
    """The settings file of this command's ``--config``, None without one."""
    return ctx.meta.get(_META_KEY)


def file_value(ctx: Any, param: str) -> Any:
    """The settings file's value of the command's parameter ``param`` (None without one). The file's
    values reach the parameters as defaults; this is for a variadic argument (``batch``'s CAPTURE…),
    which click before 8.2 fills with an empty tuple instead of looking a default up."""
    config = loaded(ctx)
    return None if config is None else config.flags.get(param)


def _from_file(ctx: Any, param: str) -> bool:
    source = ctx.get_parameter_source(param)
    return source is not None and source.name == "DEFAULT_MAP"


def solver_assignments(ctx: Any, entry: Entry, given: list[str]) -> list[str]:
    """The solver options of the settings file (checked against ``entry``), then ``given`` (``--set``)."""
    config = loaded(ctx)
    return given if config is None else [*config.solver_assignments(entry), *given]


def integrator_assignments_of(ctx: Any, entry: Entry | None, given: list[str]) -> list[str]:
    """The integrator options of the settings file (checked against ``entry``), then ``given``."""
    config = loaded(ctx)
    return given if config is None else [*config.integrator_assignments(entry), *given]


def batch_assignments(ctx: Any, solvers: list[str], given: list[str]) -> list[str]:
    """The solver options of the settings file for the batch's ``solvers``, then ``given`` (``--set``)."""
    config = loaded(ctx)
    if config is None:
        return given
    from pstoolkit.plugin.manager import get_registries

    entries = {name: get_registries().solvers.get(name) for name in dict.fromkeys(solvers)}
    return [*config.batch_assignments(entries), *given]


def check_capture(ctx: Any, capture: Path | None) -> None:
    """For a result.json given as ``--config``: a note on stderr when another version of pstoolkit
    wrote it (none with ``--quiet``), and, when the run reads the capture it names, a UserError unless
    that is the file the earlier run read (its SHA-256); a capture named on the command line is the
    user's choice. Called by the command's body, when every parameter is known."""
    config = loaded(ctx)
    if config is None:
        return
    from pstoolkit.version import __version__

    if config.from_result and config.version not in (None, __version__) and not ctx.params.get("quiet"):
        echo(f"note: {config.path} was written by pstoolkit {config.version}, this is {__version__}: results may differ", err=True)
    if capture is not None and _from_file(ctx, "capture"):
        config.check_capture(capture)
