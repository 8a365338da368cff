"""Registries: the named light models, shadow detectors, BRDFs, solvers, backends, converters and
scenes that plugins provide, each with a one-line summary and typed options."""

from __future__ import annotations

import re
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, fields
from typing import Any

from pstoolkit.errors import UserError
from pstoolkit.options import Option, parse_assignments

NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9._+-]*")
DIRECT = "(direct)"
"""The plugin name of entries registered outside a plugin hook (from a script or a test)."""


class PluginError(UserError):
    """A plugin broke a rule of the plugin system (duplicate name, malformed entry, failing hook);
    the message names the plugin(s) involved."""


@dataclass(frozen=True)
class Entry:
    """One registered thing: ``obj`` is usually a class; ``plugin`` names the plugin that registered it."""

    name: str
    obj: Any
    summary: str
    options: tuple[Option, ...]
    plugin: str
    kind: str

    def parse_options(self, pairs: Sequence[str]) -> dict[str, Any]:
        """``--set key=value`` strings → the full option dict of this entry, defaults filled in."""
        return parse_assignments(pairs, self.options, owner=f"{self.kind} {self.name!r}")


def _check_entry(kind: str, plugin: str, obj: Any, name: Any, summary: Any, options: Any) -> None:
    """Reject malformed entries at registration, so the CLI never meets one."""
    where = f"plugin {plugin!r}: {kind} {name if isinstance(name, str) and name else obj!r}"
    if not isinstance(name, str) or not NAME_PATTERN.fullmatch(name):
        raise PluginError(f"{where}: name must be a non-empty word of letters, digits, '.', '_', '+' or '-', got {name!r}")
    if not isinstance(summary, str) or not summary.strip() or "\n" in summary.strip():
        raise PluginError(f"{where}: summary must be one non-empty line, got {summary!r}")
    if not isinstance(options, tuple) or not all(isinstance(o, Option) for o in options):
        raise PluginError(f"{where}: options must be a tuple of pstoolkit.options.Option")
    seen: set[str] = set()
    for option in options:
        if option.name in seen:
            raise PluginError(f"{where}: option {option.name!r} is declared twice")
        seen.add(option.name)


class Registry:
    """Named entries of one kind (``kind`` is the human word: "solver", "light model" …)."""

    def __init__(self, kind: str) -> None:
        self.kind = kind
        self._entries: dict[str, Entry] = {}
        self._plugin = DIRECT

    @contextmanager
    def registering_for(self, plugin: str) -> Iterator[None]:
        """Attribute everything registered inside the block to ``plugin``."""
        previous, self._plugin = self._plugin, plugin
        try:
            yield
        finally:
            self._plugin = previous

    def register(
        self,
        obj: Any,
        *,
        name: str | None = None,
        summary: str | None = None,
        options: Sequence[Option] | None = None,
    ) -> Entry:
        """Add ``obj`` under ``name``; name, summary and options default to the object's attributes
        of the same names (``options`` to none). A name already taken raises PluginError naming both
        plugins."""
        name = getattr(obj, "name", None) if name is None else name
        summary = getattr(obj, "summary", None) if summary is None else summary
        raw = getattr(obj, "options", ()) if options is None else options
        opts = tuple(raw) if isinstance(raw, (list, tuple)) else raw
        plugin = self._plugin
        _check_entry(self.kind, plugin, obj, name, summary, opts)
        previous = self._entries.get(name)
        if previous is not None:
            if previous.plugin == plugin:
                raise PluginError(f"{self.kind} {name!r} is registered twice by plugin {plugin!r}")
            raise PluginError(
                f"{self.kind} {name!r} is registered by both plugin {previous.plugin!r} and plugin {plugin!r}"
            )
        entry = Entry(name=name, obj=obj, summary=summary.strip(), options=opts, plugin=plugin, kind=self.kind)
        self._entries[name] = entry
        return entry

    def get(self, name: str) -> Entry:
        """The entry called ``name``; an unknown name raises UserError listing the known ones."""
        try:
            return self._entries[name]
        except KeyError:
            known = ", ".join(self.names()) or "none registered"
            raise UserError(f"unknown {self.kind} {name!r} (known: {known})") from None

    def names(self) -> list[str]:
        return sorted(self._entries)

    def entries(self) -> list[Entry]:
        return [self._entries[n] for n in self.names()]

    def __contains__(self, name: object) -> bool:
        return name in self._entries

    def __iter__(self) -> Iterator[Entry]:
        return iter(self.entries())

    def __len__(self) -> int:
        return len(self._entries)

    def __repr__(self) -> str:
        return f"Registry({self.kind!r}, {self.names()})"


@dataclass
class Registries:
    """One registry per kind; the field name ``X`` is filled by the hook ``pstoolkit_register_X``."""

    light_models: Registry = field(default_factory=lambda: Registry("light model"))
    shadow_detectors: Registry = field(default_factory=lambda: Registry("shadow detector"))
    brdfs: Registry = field(default_factory=lambda: Registry("BRDF"))
    solvers: Registry = field(default_factory=lambda: Registry("solver"))
    backends: Registry = field(default_factory=lambda: Registry("backend"))
    converters: Registry = field(default_factory=lambda: Registry("converter"))
    scenes: Registry = field(default_factory=lambda: Registry("scene"))

    def items(self) -> list[tuple[str, Registry]]:
        """(field name, registry) pairs in declaration order."""
        return [(f.name, getattr(self, f.name)) for f in fields(self)]
