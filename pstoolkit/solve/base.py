"""The solver interface: what ``pstoolkit run --solver NAME`` calls and what it gets back.

A solver is a ``Solver`` subclass registered through ``pstoolkit_register_solvers``:

    class Flat(Solver):
        name = "flat"
        summary = "normal (0, 0, 1) everywhere"
        options = (Option("threshold", float, 0.02, "mask level"),)
        needs = frozenset({"frames"})

        def solve(self, capture, options, progress):
            ...
            return SolverResult(normal=n, mask=m, maps={"albedo": rho})
"""

from __future__ import annotations

import functools
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Collection
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

import psfmt
from psfmt.describe import names
from pstoolkit._shared.progress import Progress, no_progress
from pstoolkit.errors import UserError
from pstoolkit.plugin.options import Option, fill_defaults
from pstoolkit.plugin.registry import Entry, PluginError
from pstoolkit.solve.cluster import check_workers

INPUTS: dict[str, Callable[[psfmt.Capture], bool]] = {
    "frames": lambda c: c.frames is not None,
    "events": lambda c: c.events is not None,
    "lights": lambda c: c.lights is not None,
}
"""What a solver may declare in ``needs``, and how to tell whether a capture has it."""

DEVICES = ("auto", "cpu", "cuda")


@dataclass
class SolverResult:
    """What a solver returns, at the capture's target resolution (``psfmt.target_size``):
    ``normal`` (H, W, 3) float32 unit vectors in the camera frame (x right, y up, z to the camera),
    ``mask`` (H, W) bool where the normal is meaningful, further ``maps`` (``albedo`` (H, W, 3),
    ``roughness`` (H, W) …) and JSON-able ``diagnostics``. ``frames_used`` says how many of the
    capture's frames the solver read when it used only some (None: all of them, if it needs frames);
    the data rate of the result counts those and, if the solver needs events, the events."""

    normal: np.ndarray
    mask: np.ndarray
    maps: dict[str, np.ndarray] = field(default_factory=dict)
    diagnostics: dict[str, Any] = field(default_factory=dict)
    frames_used: int | None = None

    def __post_init__(self) -> None:
        self.normal = np.asarray(self.normal, dtype=np.float32)
        self.mask = np.asarray(self.mask, dtype=bool)
        if self.normal.ndim != 3 or self.normal.shape[2] != 3:
            raise ValueError(f"normal has shape {self.normal.shape}, expected (H, W, 3)")
        if self.mask.shape != self.normal.shape[:2]:
            raise ValueError(f"mask has shape {self.mask.shape}, expected {self.normal.shape[:2]}")

    def __repr__(self) -> str:
        # one line: the maps are megabytes of numbers
        height, width = self.mask.shape
        maps = f", maps: {names(self.maps)}" if self.maps else ""
        return f"{type(self).__name__}({height}×{width}, {int(self.mask.sum())} pixels in the mask{maps})"


class Solver(ABC):
    """Base of photometric-stereo solvers: ``name`` (registry name), ``summary`` (one line),
    ``options`` (typed, set with ``--set key=value``), ``needs`` (keys of ``INPUTS`` the capture must
    hold). ``device`` is the torch device to compute on ("cpu" or "cuda").

    A subclass writes ``solve`` for the full options dict; called from Python with only some options
    (``FramePS().solve(capture, {"robust": True})``) or none, it gets the others at their defaults
    (and ``resolve_options`` applied) and ``progress`` may be left out: ``__init_subclass__`` wraps
    each subclass's own ``solve``. An unknown key is the UserError ``--set`` gives."""

    name: ClassVar[str]
    summary: ClassVar[str]
    options: ClassVar[tuple[Option, ...]] = ()
    needs: ClassVar[Collection[str]] = frozenset()
    tiled: ClassVar[bool] = False
    """True when the solver can work in spatial tiles on Dask (``pstoolkit.solve.tiled``): it then
    honours ``scheduler`` and ``workers``, which ``pstoolkit run --scheduler/--workers`` set."""
    scheduler: str | None = None
    """Address of the Dask scheduler to send tiles to (None: a local cluster when tiling)."""
    workers: int | None = None
    """Processes of the local cluster when tiling (None: one per core)."""

    def __init__(self, device: str = "cpu") -> None:
        self.device = device

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        solve = cls.__dict__.get("solve")
        # a solver's own solve reads options["frames"] …: from Python with a partial dict it would
        # fail on a KeyError, so every subclass's solve is wrapped to see the full dict
        if solve is not None and not getattr(solve, "__isabstractmethod__", False) and not getattr(solve, "_fills_options", False):
            cls.solve = _filling_options(solve)  # type: ignore[method-assign]

    @classmethod
    def resolve_options(cls, options: dict[str, Any]) -> dict[str, Any]:
        """The options a run actually uses, which ``result.json`` records: the full ``options`` dict
        (defaults filled in) with every placeholder replaced by the value it stands for (``dualres``:
        ``epochs=-1`` → the preset's 150), so that running with the returned dict does exactly the
        same — it must be idempotent and keep the keys. Also the place to refuse, with a UserError
        naming the option, a combination that cannot apply whatever the capture (an option that only
        matters with another one off). Values that depend on the capture stay as given (the capture
        is recorded by its checksum). The default returns ``options`` unchanged."""
        return options

    @abstractmethod
    def solve(self, capture: psfmt.Capture, options: dict[str, Any], progress: Progress) -> SolverResult:
        """Estimate normals (and maps) from ``capture`` with the full ``options`` dict (defaults filled
        in, resolved by ``resolve_options``), calling ``progress`` now and then. Bad input is a
        UserError, and so is an option that cannot apply to this capture (no silent no-op)."""


def _filling_options(solve: Callable[..., SolverResult]) -> Callable[..., SolverResult]:
    """``solve`` taking a partial options dict (or None) and an optional ``progress``: the options left
    out at their defaults (``cls.options``), then ``resolve_options``, both idempotent on full dicts."""

    @functools.wraps(solve)
    def wrapper(self: Solver, capture: psfmt.Capture, options: dict[str, Any] | None = None, progress: Progress = no_progress) -> SolverResult:
        cls = type(self)
        full = fill_defaults(options or {}, cls.options, owner=f"solver {getattr(cls, 'name', cls.__name__)!r}")
        return solve(self, capture, cls.resolve_options(full), progress)

    wrapper._fills_options = True  # type: ignore[attr-defined]
    return wrapper


def check_inputs(entry: Entry, capture: psfmt.Capture) -> None:
    """UserError when the capture lacks something the solver declares in ``needs``."""
    needs = getattr(entry.obj, "needs", ())
    unknown = sorted(set(needs) - set(INPUTS))
    if unknown:
        raise PluginError(f"plugin {entry.plugin!r}: solver {entry.name!r} needs unknown input(s) {', '.join(unknown)}")
    missing = [need for need in sorted(needs) if not INPUTS[need](capture)]
    if missing:
        where = capture.path or "the capture"
        raise UserError(f"solver {entry.name!r} needs {' and '.join(missing)}, but {where} has none ({capture.kind} capture)")


def check_tiling(entry: Entry, scheduler: str | None, workers: int | None) -> None:
    """UserError when ``--scheduler`` or ``--workers`` is given for a solver that does not work in
    tiles, or ``workers`` is below 1 or given with a scheduler (``cluster.check_workers``)."""
    if scheduler is None and workers is None:
        return
    flag = "--scheduler" if scheduler is not None else "--workers"
    if not getattr(entry.obj, "tiled", False):
        raise UserError(f"{flag}: solver {entry.name!r} does not work in tiles; only a tiled solver (dualres) sends work to Dask")
    check_workers(scheduler, workers)


def resolve_device(device: str) -> str:
    """``auto`` → ``cuda`` when a GPU is usable, else ``cpu``; ``cuda`` without a GPU is a UserError."""
    if device not in DEVICES:
        raise UserError(f"--device {device!r}: expected one of {', '.join(DEVICES)}")
    if device == "cpu":
        return device
    import torch  # deferred: loading torch takes seconds and only the GPU check needs it

    if torch.cuda.is_available():
        return "cuda"
    if device == "cuda":
        raise UserError("--device cuda: no CUDA GPU is available (use --device cpu or auto)")
    return "cpu"


def input_data_rate(entry: Entry, capture: psfmt.Capture, result: SolverResult) -> float:
    """The data rate (fraction of 24 RGB frames per period) of what the solver read: its frames
    (``result.frames_used`` of them, or all) if it needs frames, the events if it needs events; a
    solver that declares neither may read anything, so the whole capture counts."""
    needs = set(getattr(entry.obj, "needs", ())) & {"frames", "events"}
    if not needs:
        return psfmt.data_rate(capture).rate
    frames = result.frames_used if "frames" in needs else 0
    return psfmt.data_rate(capture, frames=frames, events="events" in needs).rate


def resolve_options(entry: Entry, options: dict[str, Any]) -> dict[str, Any]:
    """The solver ``entry``'s ``Solver.resolve_options`` of its parsed ``options``: the values a run
    uses and records. UserError for options that cannot go together; PluginError, naming the plugin,
    when the solver returns anything but a dict with the same keys."""
    resolve = getattr(entry.obj, "resolve_options", None)
    if resolve is None:
        return dict(options)
    resolved = resolve(dict(options))
    if not isinstance(resolved, dict) or set(resolved) != set(options):
        got = sorted(resolved) if isinstance(resolved, dict) else type(resolved).__name__
        raise PluginError(
            f"plugin {entry.plugin!r}: solver {entry.name!r}: resolve_options returned {got}, expected a dict of the options {sorted(options)}"
        )
    return resolved


def run_solver(
    entry: Entry,
    capture: psfmt.Capture,
    options: dict[str, Any],
    *,
    device: str = "cpu",
    scheduler: str | None = None,
    workers: int | None = None,
    progress: Progress = no_progress,
) -> tuple[SolverResult, float]:
    """Run the registered solver ``entry`` on ``capture`` with its ``options`` (resolved here too,
    ``resolve_options``, which is idempotent: a caller may pass them resolved already); returns its
    result and the wall seconds. ``options`` may leave options out: they take their defaults (an
    unknown key is a UserError, as with ``--set``). ``scheduler`` and ``workers`` go to a solver
    that works in tiles (``Solver.tiled``; for any other a UserError). A result of the wrong type or
    size is a PluginError naming the plugin."""
    check_inputs(entry, capture)
    check_tiling(entry, scheduler, workers)
    options = fill_defaults(options, entry.options, owner=f"{entry.kind} {entry.name!r}")
    options = resolve_options(entry, options)
    solver = entry.obj(device=device)
    solver.scheduler, solver.workers = scheduler, workers
    start = time.perf_counter()
    result = solver.solve(capture, options, progress)
    seconds = time.perf_counter() - start
    blame = f"plugin {entry.plugin!r}: solver {entry.name!r}"
    if not isinstance(result, SolverResult):
        raise PluginError(f"{blame} returned {type(result).__name__}, expected SolverResult")
    expected = psfmt.target_size(capture)
    if result.normal.shape[:2] != expected:
        raise PluginError(f"{blame} returned a {result.normal.shape[:2]} normal map, expected {expected}")
    return result, seconds
