"""The plugin manager: finds plugins through the entry-point group ``pstoolkit``, lets each one fill
the registries through its hooks, and records who registered what and which plugins failed.

First-party plugins (``plugins/``) are found exactly like third-party ones, through the entry points
of the ``pstoolkit`` distribution; they are *built in*: always loaded, first, and their names win a
clash (a third party's entry under a built-in name is ignored with a warning). Environment, for third
parties only: ``PSTOOLKIT_DISABLE_PLUGIN_AUTOLOAD=1`` loads none of their entry points (register
plugins with ``register_plugin``); ``PSTOOLKIT_PLUGINS=mine,other`` loads only the named ones.
"""

from __future__ import annotations

import os
import sys
import types
from contextlib import nullcontext
from dataclasses import dataclass, field
from importlib.metadata import EntryPoint, entry_points
from typing import TYPE_CHECKING, Any

import pluggy

from pstoolkit.plugin import spec as hookspecs
from pstoolkit.plugin.registry import PluginError, Registries, Registry
from pstoolkit.plugin.spec import PROJECT, hookimpl

if TYPE_CHECKING:
    import typer

__all__ = [
    "ALLOW_ENV",
    "DISABLE_ENV",
    "ENTRY_POINT_GROUP",
    "Failure",
    "PluginInfo",
    "add_commands",
    "get_registries",
    "hookimpl",
    "load_failures",
    "loaded_plugins",
    "register_plugin",
    "reset",
]

ENTRY_POINT_GROUP = PROJECT
DISABLE_ENV = "PSTOOLKIT_DISABLE_PLUGIN_AUTOLOAD"
ALLOW_ENV = "PSTOOLKIT_PLUGINS"
BUILT_IN_DISTRIBUTION = "pstoolkit"
"""The distribution whose entry points are the built-in plugins."""
BUILT_IN = "built in"
_OFF = {"", "0", "false", "no", "off"}


@dataclass(frozen=True)
class PluginInfo:
    """A loaded plugin: its name (the entry-point name), the module or object behind it, the version
    of the distribution that provides it, and how it was found."""

    name: str
    module: str
    version: str | None
    source: str

    @property
    def built_in(self) -> bool:
        return self.source == BUILT_IN


@dataclass(frozen=True)
class Failure:
    """A plugin that could not be loaded, or whose hook raised; ``error`` is one line."""

    plugin: str
    error: str


@dataclass
class _State:
    manager: pluggy.PluginManager
    plugins: list[PluginInfo] = field(default_factory=list)
    failures: list[Failure] = field(default_factory=list)
    registries: Registries | None = None

    def fail(self, plugin: str, error: str) -> None:
        """Record a failure and warn once on stderr, so a broken plugin never stops the others."""
        self.failures.append(Failure(plugin, error))
        print(f"pstoolkit: warning: plugin {plugin!r}: {error}", file=sys.stderr)


_state: _State | None = None
_explicit: dict[str, tuple[object, str | None]] = {}


def _error_line(exc: BaseException) -> str:
    lines = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {lines[0]}" if lines else type(exc).__name__


def _describe(plugin: object) -> str:
    if isinstance(plugin, types.ModuleType):
        return plugin.__name__
    cls = plugin if isinstance(plugin, type) else type(plugin)
    return f"{cls.__module__}.{cls.__qualname__}"


def _autoload_disabled() -> bool:
    return os.environ.get(DISABLE_ENV, "").strip().lower() not in _OFF


def _allow_list() -> set[str] | None:
    names = {n.strip() for n in os.environ.get(ALLOW_ENV, "").split(",") if n.strip()}
    return names or None


def _is_built_in(ep: EntryPoint) -> bool:
    dist = ep.dist.name if ep.dist is not None else ""
    return dist.lower().replace("_", "-") == BUILT_IN_DISTRIBUTION


def _add(state: _State, plugin: object, name: str, version: str | None, source: str) -> None:
    pm = state.manager
    if pm.has_plugin(name):
        state.fail(name, f"another plugin is already called {name!r} ({_describe(pm.get_plugin(name))})")
        return
    try:
        pm.register(plugin, name=name)
    except (ValueError, pluggy.PluginValidationError) as exc:
        state.fail(name, f"cannot register {_describe(plugin)}: {_error_line(exc)}")
        return
    unknown = sorted(h.name for h in pm.get_hookcallers(plugin) or () if h.spec is None)
    if unknown:
        pm.unregister(plugin)
        state.fail(name, f"implements unknown hook(s) {', '.join(unknown)} (see docs/hooks.md)")
        return
    state.plugins.append(PluginInfo(name, _describe(plugin), version, source))


def _load() -> _State:
    state = _State(pluggy.PluginManager(PROJECT))
    state.manager.add_hookspecs(hookspecs)
    third_parties = not _autoload_disabled()
    allowed = _allow_list() if third_parties else None
    # built-in plugins first, so that their names are taken before any third party's
    found = sorted(entry_points(group=ENTRY_POINT_GROUP), key=lambda ep: (not _is_built_in(ep), ep.name))
    for ep in found:
        built_in = _is_built_in(ep)
        if not built_in and (not third_parties or (allowed is not None and ep.name not in allowed)):
            continue
        try:
            plugin = ep.load()
        except Exception as exc:  # any import-time error of a plugin must not stop the others
            state.fail(ep.name, f"cannot import {ep.value!r}: {_error_line(exc)}")
            continue
        version = ep.dist.version if ep.dist is not None else None
        _add(state, plugin, ep.name, version, BUILT_IN if built_in else "entry point")
    for missing in sorted((allowed or set()) - {ep.name for ep in found}):
        state.fail(missing, f"named in {ALLOW_ENV} but no installed package provides it")
    for name, (plugin, version) in _explicit.items():
        _add(state, plugin, name, version or getattr(plugin, "__version__", None), "registered")
    return state


def _state_now() -> _State:
    global _state
    if _state is None:
        _state = _load()
    return _state


def _caller(state: _State, hook: str, plugin: str) -> pluggy.HookCaller:
    """The hook restricted to one plugin, so whatever it registers is attributed to it."""
    others = [p for n, p in state.manager.list_name_plugin() if n != plugin]
    return state.manager.subset_hook_caller(hook, others)


def _call_each(state: _State, hook: str, **kwargs: Any) -> None:
    """Call ``hook`` plugin by plugin; a ``registry`` argument attributes entries to the caller."""
    registry: Registry | None = kwargs.get("registry")
    for info in state.plugins:
        with registry.registering_for(info.name, built_in=info.built_in) if registry is not None else nullcontext():
            try:
                _caller(state, hook, info.name)(**kwargs)
            except PluginError:
                raise
            except Exception as exc:  # a faulty plugin is reported and skipped, the rest still run
                state.fail(info.name, f"{hook} failed: {_error_line(exc)}")
        if registry is not None:
            for plugin, message in registry.take_ignored():
                state.fail(plugin, message)


def get_registries() -> Registries:
    """The registries filled by every loaded plugin (built once, then cached until ``reset``).
    A name registered by two plugins raises PluginError naming both."""
    state = _state_now()
    if state.registries is None:
        registries = Registries()
        for kind, registry in registries.items():
            _call_each(state, f"pstoolkit_register_{kind}", registry=registry)
        state.registries = registries
    return state.registries


def add_commands(app: typer.Typer) -> None:
    """Let every loaded plugin add its commands to ``app`` (the ``pstoolkit_add_commands`` hook)."""
    _call_each(_state_now(), "pstoolkit_add_commands", app=app)


def loaded_plugins() -> list[PluginInfo]:
    """Plugins in load order: entry points by name, then explicitly registered ones."""
    return list(_state_now().plugins)


def load_failures() -> list[Failure]:
    """Plugins that failed to import or register, and hooks that raised, so far."""
    return list(_state_now().failures)


def register_plugin(plugin: object, name: str, version: str | None = None) -> None:
    """Register a plugin module or object without an entry point (scripts, tests, or with
    autoloading disabled). Registries are rebuilt on next use."""
    global _state
    if name in _explicit:
        raise PluginError(f"plugin {name!r} is already registered")
    _explicit[name] = (plugin, version)
    _state = None


def reset() -> None:
    """Forget loaded state and explicitly registered plugins; the next use reloads from scratch."""
    global _state
    _state = None
    _explicit.clear()
