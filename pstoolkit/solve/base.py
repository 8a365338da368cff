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

import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Collection
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

import psfmt
from pstoolkit.errors import UserError
from pstoolkit.plugin.options import Option
from pstoolkit.plugin.registry import Entry, PluginError

Progress = Callable[[float, str], None]
"""``progress(fraction, message)``: fraction of the work done in [0, 1] and what is happening."""

INPUTS: dict[str, Callable[[psfmt.Capture], bool]] = {
    "frames": lambda c: c.frames is not None,
    "events": lambda c: c.events is not None,
    "lights": lambda c: c.lights is not None,
}
"""What a solver may declare in ``needs``, and how to tell whether a capture has it."""

DEVICES = ("auto", "cpu", "cuda")


def no_progress(fraction: float, message: str) -> None:
    """The progress callback that reports nowhere."""


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


class Solver(ABC):
    """Base of photometric-stereo solvers: ``name`` (registry name), ``summary`` (one line),
    ``options`` (typed, set with ``--set key=value``), ``needs`` (keys of ``INPUTS`` the capture must
    hold). ``device`` is the torch device to compute on ("cpu" or "cuda")."""

    name: ClassVar[str]
    summary: ClassVar[str]
    options: ClassVar[tuple[Option, ...]] = ()
    needs: ClassVar[Collection[str]] = frozenset()

    def __init__(self, device: str = "cpu") -> None:
        self.device = device

    @abstractmethod
    def solve(self, capture: psfmt.Capture, options: dict[str, Any], progress: Progress) -> SolverResult:
        """Estimate normals (and maps) from ``capture`` with the full ``options`` dict (defaults filled
        in), calling ``progress`` now and then. Bad input is a UserError."""


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


def run_solver(
    entry: Entry,
    capture: psfmt.Capture,
    options: dict[str, Any],
    *,
    device: str = "cpu",
    progress: Progress = no_progress,
) -> tuple[SolverResult, float]:
    """Run the registered solver ``entry`` on ``capture``; returns its result and the wall seconds.
    A result of the wrong type or size is a PluginError naming the plugin."""
    check_inputs(entry, capture)
    solver = entry.obj(device=device)
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
