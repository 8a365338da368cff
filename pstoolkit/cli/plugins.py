"""``pstoolkit plugins``: every plugin with its version and what it registered, and load failures."""

from __future__ import annotations

import json
from typing import Any

import typer

from pstoolkit.cli.app import QUIET_HELP, app, echo
from pstoolkit.plugin.manager import PluginInfo, get_registries, load_failures, loaded_plugins
from pstoolkit.plugin.options import Option
from pstoolkit.plugin.registry import Entry, Registry

Holdings = list[tuple[str, Registry, list[Entry]]]


def _holdings(plugin: str) -> Holdings:
    """(field name, registry, entries) for each registry the plugin added to."""
    held = [(kind, registry, [e for e in registry if e.plugin == plugin]) for kind, registry in get_registries().items()]
    return [h for h in held if h[2]]


def _option(o: Option) -> dict[str, Any]:
    return {
        "name": o.name,
        "type": o.type.__name__,
        "default": o.default,
        "help": o.help,
        "choices": list(o.choices) if o.choices is not None else None,
        "minimum": o.minimum,
        "maximum": o.maximum,
        "multiple": o.multiple,
    }


def _plugin_json(info: PluginInfo, held: Holdings) -> dict[str, Any]:
    return {
        "name": info.name,
        "version": info.version,
        "module": info.module,
        "source": info.source,
        "registered": {
            kind: [{"name": e.name, "summary": e.summary, "options": [_option(o) for o in e.options]} for e in entries]
            for kind, _, entries in held
        },
    }


OPTION_FLAGS = {"renderers": "--render-set"}
"""The flag that sets an entry's options where it is not ``--set`` (``simulate --renderer``'s)."""


def _plugin_text(info: PluginInfo, held: Holdings) -> list[str]:
    lines = [f"{info.name} {info.version or '(no version)'}  ({info.module}, {info.source})"]
    for kind, registry, entries in held:
        flag = OPTION_FLAGS.get(kind, "--set")
        lines.append(f"  {registry.kind}s:")
        width = max(len(e.name) for e in entries)
        for e in entries:
            lines.append(f"    {e.name:<{width}}  {e.summary}")
            lines.extend(f"      {flag} {o.describe()}" for o in e.options)
    if not held:
        lines.append("  (registers no entries)")
    return lines


@app.command()
def plugins(
    as_json: bool = typer.Option(False, "--json", help="Print the listing as JSON."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help=QUIET_HELP),
) -> None:
    """List every plugin with its version and what it registered (light models, shadow detectors,
    BRDFs, solvers, backends, converters, scenes, integrators, renderers, light calibrations) with options, and plugins that failed
    to load."""
    listing = [(info, _holdings(info.name)) for info in loaded_plugins()]
    failures = load_failures()
    if as_json:
        doc = {
            "plugins": [_plugin_json(info, held) for info, held in listing],
            "failures": [{"plugin": f.plugin, "error": f.error} for f in failures],
        }
        echo(json.dumps(doc, indent=2, default=str))
        return
    lines = [line for info, held in listing for line in _plugin_text(info, held)] or ["no plugins loaded"]
    if failures:
        lines.append("failed:")
        lines.extend(f"  {f.plugin}: {f.error}" for f in failures)
    echo("\n".join(lines))
