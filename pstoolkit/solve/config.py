"""Settings files for ``pstoolkit run --config FILE`` and ``pstoolkit batch --config FILE``
(``docs/config.md``).

FILE is a TOML file whose keys are the command's flags without their dashes (``solver``, ``out``,
``device``, ``error-max`` …), the CAPTURE argument(s) as ``capture`` (``captures`` for batch), and the
solver's options as a ``[options]`` table of typed values or a ``set = ["key=value", …]`` array, both
checked against the same typed options as ``--set`` (``pstoolkit.plugin.options``). Relative paths
are relative to the file's folder. For ``run``, FILE may also be the ``result.json`` of an earlier
run: its solver, options (as resolved), name, error-map scale and capture, whose SHA-256 must still be
the recorded one. Every error is one UserError line naming the file and the key.

The command line overrides the file: the CLI layer (``pstoolkit.cli.config``) gives the file's flag
values to the command as defaults, and puts the file's option assignments before those of ``--set``,
where the later assignment of a key wins.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pstoolkit.errors import UserError
from pstoolkit.io.checksum import file_sha256
from pstoolkit.io.textdata import read_json, read_toml
from pstoolkit.plugin.options import table_assignments, value_kind
from pstoolkit.plugin.registry import Entry

RESULT_SUFFIX = ".json"
"""A FILE with this suffix is read as an earlier run's result.json, any other as TOML."""

# kind of each flag's value: "str", "path", "float", "int", "bool", or "strs"/"paths" (one or an array)
RUN_FLAGS = {
    "capture": ("capture", "path"),
    "solver": ("solver", "str"),
    "out": ("out", "path"),
    "device": ("device", "str"),
    "scheduler": ("scheduler", "str"),
    "workers": ("workers", "int"),
    "name": ("name", "str"),
    "error-max": ("error_max", "float"),
    "integrate": ("integrate", "str"),
    "store": ("store", "bool"),
}
"""``run``'s settings: key in the file → (the command's parameter, kind of value)."""

BATCH_FLAGS = {
    "captures": ("captures", "paths"),
    "solver": ("solvers", "strs"),
    "out": ("out", "path"),
    "scheduler": ("scheduler", "str"),
    "workers": ("workers", "int"),
    "device": ("device", "str"),
    "error-max": ("error_max", "float"),
}
"""``batch``'s settings: key in the file → (the command's parameter, kind of value)."""

OPTION_KEYS = {
    "run": ("set", "options", "integrator-set", "integrator-options"),
    "batch": ("set", "options"),
}
"""Keys of option assignments, per command: the solver's (``set`` strings, ``options`` table) and
the integrator's of ``run --integrate``."""

_KINDS = {"str": (str, "a string"), "path": (str, "a path (string)"), "float": ((int, float), "a number"),
          "int": (int, "an integer"), "bool": (bool, "true or false")}


@dataclass
class CommandConfig:
    """A settings file read for one command.

    ``flags`` maps the command's parameter names to the file's values (paths absolute), to become the
    command's defaults; ``solver_set`` and ``solver_table`` are the file's solver options (``set``
    strings as given, the ``[options]`` table of typed values), ``integrator_set`` and
    ``integrator_table`` those of the integrator (``run``). A result.json gives ``capture_sha256``
    (None when it records none), ``version`` (the toolkit that wrote it) and ``from_result``."""

    path: Path
    command: str
    flags: dict[str, Any] = field(default_factory=dict)
    solver_set: list[str] = field(default_factory=list)
    solver_table: dict[str, Any] = field(default_factory=dict)
    integrator_set: list[str] = field(default_factory=list)
    integrator_table: dict[str, Any] = field(default_factory=dict)
    capture_sha256: str | None = None
    version: str | None = None
    from_result: bool = False

    def fail(self, key: str, message: str) -> UserError:
        """The one-line error about ``key`` of this file."""
        return UserError(f"{self.path}: {key}: {message}")

    def solver_assignments(self, entry: Entry) -> list[str]:
        """The file's options of the solver ``entry`` as ``key=value`` strings (``set`` first, then the
        ``[options]`` table), checked against its typed options; errors name the file and the key."""
        return self._assignments(entry, self.solver_set, self.solver_table, "set", "options")

    def integrator_assignments(self, entry: Entry | None) -> list[str]:
        """The file's options of the integrator ``entry`` (``run --integrate``); without an integrator
        they are returned unchecked, for the command to refuse them."""
        if entry is None:
            return [*self.integrator_set, *(f"{k}={v}" for k, v in self.integrator_table.items())]
        return self._assignments(entry, self.integrator_set, self.integrator_table, "integrator-set", "integrator-options")

    def _assignments(self, entry: Entry, given: list[str], table: dict[str, Any], set_key: str, table_key: str) -> list[str]:
        try:
            entry.parse_options(given)
        except UserError as exc:
            raise self.fail(set_key, str(exc)) from None
        pairs = table_assignments(table, entry.options, f"{entry.kind} {entry.name!r}", f"{self.path}: {table_key}")
        try:
            entry.parse_options(pairs)  # a nested option's settings are checked by its owner here
        except UserError as exc:
            raise self.fail(table_key, str(exc)) from None
        return [*given, *pairs]

    def batch_assignments(self, entries: dict[str, Entry]) -> list[str]:
        """The file's options for ``batch`` with the solvers ``entries`` (name → entry) as ``key=value``
        and ``SOLVER.key=value`` strings: ``set`` as given, then ``[options]``, whose plain keys set
        every listed solver that has the option (``--set key=value``) and whose ``[options.NAME]``
        tables set solver NAME only — skipped when NAME is a registered solver this batch does not
        run, so one file can serve several choices of ``--solver``."""
        from pstoolkit.plugin.manager import get_registries
        from pstoolkit.solve.batch import solver_options

        try:
            solver_options(list(entries), self.solver_set)
        except UserError as exc:
            raise self.fail("set", str(exc)) from None
        pairs: list[str] = []
        for key, value in self.solver_table.items():
            if key in entries and isinstance(value, dict):
                entry = entries[key]
                inner = table_assignments(value, entry.options, f"solver {key!r}", f"{self.path}: options.{key}")
                pairs += [f"{key}.{pair}" for pair in inner]
                continue
            takers = [entry for entry in entries.values() if any(o.name == key for o in entry.options)]
            if not takers:
                if isinstance(value, dict) and key in get_registries().solvers:
                    continue  # the options of a solver that this batch does not run
                raise self.fail(f"options.{key}", f"none of the solvers {', '.join(entries)} has an option {key!r}")
            for entry in takers:  # checked against each solver's own option, and given to it by name
                found = table_assignments({key: value}, entry.options, f"solver {entry.name!r}", f"{self.path}: options")
                pairs += [f"{entry.name}.{pair}" for pair in found]
        try:
            solver_options(list(entries), pairs)
        except UserError as exc:
            raise self.fail("options", str(exc)) from None
        return [*self.solver_set, *pairs]

    def check_capture(self, capture: Path) -> None:
        """For a result.json: UserError unless ``capture`` (the recorded one) is the file that run
        read, by its SHA-256. A result.json that records no checksum (written before they were) is
        refused too: name the capture on the command line to run on it anyway."""
        if not self.from_result:
            return
        if self.capture_sha256 is None:
            raise self.fail(
                "capture_sha256",
                f"not recorded (written by pstoolkit {self.version or 'unknown'}), so {capture} cannot be checked; "
                "give the capture on the command line to run on it anyway",
            )
        if not capture.is_file():
            raise self.fail("capture", f"{capture}: no such file")
        digest = file_sha256(capture)
        if digest != self.capture_sha256:
            raise self.fail(
                "capture_sha256",
                f"{capture} is not the file that run read (changed since, or replaced): its SHA-256 is {digest[:12]}…, "
                f"the run recorded {self.capture_sha256[:12]}…; give the capture on the command line to run on it anyway",
            )


def read_config(path: Path, command: str) -> CommandConfig:
    """Read and check the settings file ``path`` for ``command`` (``run`` or ``batch``): a TOML file,
    or for ``run`` a result.json (by its ``.json`` suffix). UserError, naming the file and the key, for
    a file that cannot be read or parsed, an unknown key, a value of the wrong type, or an unknown
    solver or integrator; the solver options are checked when the solver is known
    (``CommandConfig.solver_assignments``)."""
    if not path.is_file():
        raise UserError(f"{path}: {'not a file' if path.exists() else 'no such file'}")
    if path.suffix.lower() == RESULT_SUFFIX:
        if command != "run":
            raise UserError(f"{path}: a result.json describes one run; repeat it with `pstoolkit run --config {path}`")
        return _read_result(path)
    data = read_toml(path)
    config = CommandConfig(path, command)
    flags = RUN_FLAGS if command == "run" else BATCH_FLAGS
    option_keys = OPTION_KEYS[command]
    for key, value in data.items():
        if key in flags:
            param, kind = flags[key]
            config.flags[param] = _flag_value(config, key, value, kind)
        elif key in option_keys:
            _option_value(config, key, value)
        else:
            known = ", ".join(sorted([*flags, *option_keys]))
            raise UserError(f"{path}: unknown key {key!r} (keys: {known})")
    _check_names(config)
    return config


def _flag_value(config: CommandConfig, key: str, value: Any, kind: str) -> Any:
    """A flag's value checked against its kind; paths made absolute against the file's folder."""
    if kind in ("strs", "paths"):
        items = value if isinstance(value, list) else [value]
        single = "str" if kind == "strs" else "path"
        if not items:
            raise config.fail(key, "expected at least one value, got an empty array")
        return [_flag_value(config, key, item, single) for item in items]
    types, expected = _KINDS[kind]
    if not isinstance(value, types) or (kind in ("int", "float") and isinstance(value, bool)):
        raise config.fail(key, f"expected {expected}, got {value_kind(value)} {value!r}")
    if kind == "float":
        return float(value)
    if kind == "path":
        # absolute and without "..": what result.json records, whatever the working folder
        return Path(os.path.abspath(config.path.parent / Path(value).expanduser()))
    return value


def _option_value(config: CommandConfig, key: str, value: Any) -> None:
    if key.endswith("set"):
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            raise config.fail(key, f'expected an array of "key=value" strings, got {value_kind(value)} {value!r}')
        if key == "set":
            config.solver_set = list(value)
        else:
            config.integrator_set = list(value)
        return
    if not isinstance(value, dict):
        raise config.fail(key, f"expected a table of options, got {value_kind(value)} {value!r}")
    if key == "options":
        config.solver_table = value
    else:
        config.integrator_table = value


def _check_names(config: CommandConfig) -> None:
    """Unknown solvers and integrators named by the file are its errors, whatever the command line says."""
    from pstoolkit.plugin.manager import get_registries

    registries = get_registries()
    names = config.flags.get("solver") or config.flags.get("solvers") or []
    for name in [names] if isinstance(names, str) else names:
        try:
            registries.solvers.get(name)
        except UserError as exc:
            raise config.fail("solver", str(exc)) from None
    integrator = config.flags.get("integrate")
    if integrator is not None:
        try:
            registries.integrators.get(integrator)
        except UserError as exc:
            raise config.fail("integrate", str(exc)) from None


def _read_result(path: Path) -> CommandConfig:
    """``run``'s settings from an earlier run's result.json: solver, options, capture (and its
    checksum), name and error-map scale; its other keys (scores, seconds …) are not settings."""
    data = read_json(path)
    if not isinstance(data, dict) or not isinstance(data.get("solver"), str) or "capture" not in data:
        raise UserError(f"{path}: not a result.json written by `pstoolkit run` (no solver and capture)")
    config = CommandConfig(path, "run", from_result=True)
    config.flags["solver"] = data["solver"]
    capture = data["capture"]
    if not isinstance(capture, str):
        raise config.fail("capture", f"expected a path (string), got {value_kind(capture)} {capture!r}")
    # as recorded: absolute since checksums are (a relative one is relative to where that run ran)
    config.flags["capture"] = Path(capture)
    options = data.get("options", {})
    if not isinstance(options, dict):
        raise config.fail("options", f"expected a table of options, got {value_kind(options)} {options!r}")
    config.solver_table = options
    if isinstance(data.get("name"), str):
        config.flags["name"] = data["name"]
    if isinstance(data.get("error_max_deg"), (int, float)) and not isinstance(data["error_max_deg"], bool):
        config.flags["error_max"] = float(data["error_max_deg"])
    digest = data.get("capture_sha256")
    if digest is not None and not isinstance(digest, str):
        raise config.fail("capture_sha256", f"expected a string, got {value_kind(digest)} {digest!r}")
    config.capture_sha256 = digest
    version = data.get("pstoolkit_version")
    config.version = version if isinstance(version, str) else None
    _check_names(config)
    return config
