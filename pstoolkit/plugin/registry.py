"""Registries: the named light models, shadow detectors, BRDFs, solvers, backends, converters,
scenes, normal integrators, independent renderers and light calibrations that plugins provide, each with a
one-line summary and typed options."""

from __future__ import annotations

import importlib
import re
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, fields
from typing import Any

from pstoolkit.errors import UserError
from pstoolkit.plugin.options import Option, parse_assignments

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
        raise PluginError(f"{where}: options must be a tuple of pstoolkit.plugin.options.Option")
    seen: set[str] = set()
    for option in options:
        if option.name in seen:
            raise PluginError(f"{where}: option {option.name!r} is declared twice")
        seen.add(option.name)


def _resolve(base: str) -> tuple[type, ...]:
    """``"module:Name|module:Other"`` → the classes, imported now (bases that load torch stay unloaded
    until something of their kind is registered)."""
    classes = []
    for spec in base.split("|"):
        module, _, name = spec.partition(":")
        classes.append(getattr(importlib.import_module(module), name))
    return tuple(classes)


class Registry:
    """Named entries of one kind (``kind`` is the human word: "solver", "light model" …).

    ``base`` (``"module:Class"``, several joined by ``|``) is the class every registered object must
    subclass; anything else is refused at registration with a PluginError naming the plugin, so a
    solver registered as a BRDF never reaches a command."""

    def __init__(self, kind: str, base: str | None = None) -> None:
        self.kind = kind
        self.base = base
        self._entries: dict[str, Entry] = {}
        self._plugin = DIRECT
        self._built_in = False
        self._built_in_plugins: set[str] = set()
        self._ignored: list[tuple[str, str]] = []

    @contextmanager
    def registering_for(self, plugin: str, built_in: bool = False) -> Iterator[None]:
        """Attribute everything registered inside the block to ``plugin``; a ``built_in`` plugin's
        names win a clash with a third party's."""
        previous = self._plugin, self._built_in
        self._plugin, self._built_in = plugin, built_in
        try:
            yield
        finally:
            self._plugin, self._built_in = previous

    def take_ignored(self) -> list[tuple[str, str]]:
        """(plugin, one-line message) for each third-party entry ignored since the last call because
        a built-in plugin holds its name."""
        ignored, self._ignored = self._ignored, []
        return ignored

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
        plugins, unless a built-in plugin holds it and a third party asks: then the third party's
        entry is ignored (``take_ignored`` reports it) and the built-in entry returned."""
        name = getattr(obj, "name", None) if name is None else name
        summary = getattr(obj, "summary", None) if summary is None else summary
        raw = getattr(obj, "options", ()) if options is None else options
        opts = tuple(raw) if isinstance(raw, (list, tuple)) else raw
        plugin = self._plugin
        self._check_kind(plugin, obj, name)
        _check_entry(self.kind, plugin, obj, name, summary, opts)
        previous = self._entries.get(name)
        if previous is not None:
            if previous.plugin == plugin:
                raise PluginError(f"{self.kind} {name!r} is registered twice by plugin {plugin!r}")
            if previous.plugin in self._built_in_plugins and not self._built_in:
                self._ignored.append((plugin, f"{self.kind} {name!r} is built in (plugin {previous.plugin!r}); this plugin's entry is ignored"))
                return previous
            raise PluginError(
                f"{self.kind} {name!r} is registered by both plugin {previous.plugin!r} and plugin {plugin!r}"
            )
        entry = Entry(name=name, obj=obj, summary=summary.strip(), options=opts, plugin=plugin, kind=self.kind)
        self._entries[name] = entry
        if self._built_in:
            self._built_in_plugins.add(plugin)
        return entry

    def _check_kind(self, plugin: str, obj: Any, name: Any) -> None:
        if self.base is None:
            return
        bases = _resolve(self.base)
        if not (isinstance(obj, type) and issubclass(obj, bases)):
            wanted = " or ".join(f"{b.__module__}.{b.__qualname__}" for b in bases)
            what = f"{obj.__module__}.{obj.__qualname__}" if isinstance(obj, type) else repr(obj)[:80]
            raise PluginError(f"plugin {plugin!r}: {self.kind} {name!r} is {what}, not a subclass of {wanted}")

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

    light_models: Registry = field(default_factory=lambda: Registry("light model", "pstoolkit.optics.lights:LightModel"))
    shadow_detectors: Registry = field(default_factory=lambda: Registry("shadow detector", "pstoolkit.shadows.base:ShadowDetector"))
    brdfs: Registry = field(default_factory=lambda: Registry("BRDF", "pstoolkit.optics.brdf:BRDF"))
    solvers: Registry = field(default_factory=lambda: Registry("solver", "pstoolkit.solve.base:Solver"))
    backends: Registry = field(default_factory=lambda: Registry(
        "backend", "pstoolkit.hardware.backend:LightBackend|pstoolkit.hardware.backend:CameraSource"))
    converters: Registry = field(default_factory=lambda: Registry("converter", "pstoolkit.io.converter:Converter"))
    scenes: Registry = field(default_factory=lambda: Registry("scene", "pstoolkit.sim.scenes:Scene"))
    integrators: Registry = field(default_factory=lambda: Registry("integrator", "pstoolkit.surface.base:Integrator"))
    renderers: Registry = field(default_factory=lambda: Registry("renderer", "pstoolkit.sim.renderers:SceneRenderer"))
    light_calibrations: Registry = field(default_factory=lambda: Registry("light calibration", "pstoolkit.hardware.lightcal:LightCalibration"))

    def items(self) -> list[tuple[str, Registry]]:
        """(field name, registry) pairs in declaration order."""
        return [(f.name, getattr(self, f.name)) for f in fields(self)]
