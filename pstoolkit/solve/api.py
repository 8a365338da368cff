"""The Python API of ``pstoolkit run``: ``pstoolkit.solve_capture(capture, "frameps", robust=True)``.

    import psfmt, pstoolkit

    with psfmt.read("blobs.h5") as capture:
        result = pstoolkit.solve_capture(capture, "frameps", robust=True)   # a Solution
    result.normal, result.mask, result.maps          # what the solver returned (a SolverResult)
    result.score.stats["mae_deg"], result.seconds    # its score against the ground truth, its time
    surface = result.integrate("poisson")            # a pstoolkit.surface.Surface
    result.write("out/blobs-frameps")                # the folder `pstoolkit run` writes

``solve_capture`` takes the solver by its registry name and its options as keyword arguments, checked
against the registry entry's typed options exactly as ``--set`` checks them (the values are given
to the same parser, so the errors are the same), the others at their defaults.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

import psfmt
from psfmt.describe import names
from pstoolkit._shared.progress import Progress, no_progress
from pstoolkit.errors import UserError
from pstoolkit.plugin.manager import get_registries
from pstoolkit.plugin.registry import Entry
from pstoolkit.solve.base import SolverResult, input_data_rate, resolve_device, resolve_options, run_solver

if TYPE_CHECKING:
    from pstoolkit.evaluation.scoring import Score
    from pstoolkit.surface.base import Surface


def _text(value: Any) -> str:
    """A Python value as the ``--set`` text that parses back to it (bools as true/false, floats
    through ``repr``, which round-trips)."""
    if isinstance(value, (bool, np.bool_)):
        return "true" if value else "false"
    if isinstance(value, (float, np.floating)):
        return repr(float(value))
    if isinstance(value, np.integer):
        return str(int(value))
    return str(value)


def assignments(entry: Entry, values: Mapping[str, Any]) -> list[str]:
    """Keyword options → the ``key=value`` strings of ``--set``, for ``entry.parse_options``. A
    multiple option takes one value or a list/tuple of them; a nested one (``dualres``'s ``shadow``)
    a dict of its entry's options, or ``"key=value"`` strings; ``**{"shadow.threshold": 0.2}`` works
    as on the command line."""
    known = {option.name: option for option in entry.options}
    pairs: list[str] = []
    for key, value in values.items():
        option = known.get(key)
        if option is not None and option.nested:
            if isinstance(value, Mapping):
                pairs += [f"{key}.{inner}={_text(setting)}" for inner, setting in value.items()]
            else:
                pairs += [f"{key}.{inner}" for inner in ([value] if isinstance(value, str) else value)]
        elif option is not None and option.multiple and isinstance(value, (list, tuple)):
            pairs += [f"{key}={_text(item)}" for item in value]
        else:
            # an unknown key too: parse_options raises the error --set gives for it
            pairs.append(f"{key}={_text(value)}")
    return pairs


@dataclass(kw_only=True, repr=False)
class Solution(SolverResult):
    """A ``SolverResult`` (``normal`` (H, W, 3) float32 unit vectors, zero outside ``mask`` as
    ``pstoolkit run`` writes it; ``mask`` (H, W) bool; ``maps``; ``diagnostics``; ``frames_used``)
    with how it was made: the registry ``entry`` of the solver, the full ``options`` it ran with
    (defaults filled in, ``resolve_options`` applied), the torch ``device``, the wall ``seconds`` of
    the solve, the ``data_rate`` of what it read (share of 24 RGB frames per light period), its
    ``score`` against the capture's ground truth (``pstoolkit.evaluation.scoring.Score``: per-pixel
    errors in degrees and the statistics of ``result.json``; None without ground truth), the capture's
    ``capture_kind`` and absolute ``capture_path`` (None for a capture made in memory) and its
    ``calibration`` (for the camera of ``integrate``)."""

    entry: Entry
    options: dict[str, Any]
    device: str
    seconds: float
    data_rate: float
    score: Score | None
    capture_kind: str
    capture_path: Path | None
    calibration: psfmt.Calibration = field(default_factory=psfmt.Calibration)

    @property
    def solver(self) -> str:
        """The solver's registry name."""
        return self.entry.name

    def __repr__(self) -> str:
        height, width = self.mask.shape
        stats = self.score.stats if self.score is not None else None
        scored = "no ground truth" if stats is None else f"MAE {stats['mae_deg']:.2f}°, coverage {100 * stats['coverage']:.1f} %"
        maps = f", maps: {names(self.maps)}" if self.maps else ""
        return f"Solution({self.solver!r}, {height}×{width}, {scored}, {self.seconds:.3g} s, data rate {100 * self.data_rate:.1f} %{maps})"

    def integrate(self, integrator: str = "poisson", **options: Any) -> Surface:
        """The surface of the normal map by a registered integrator (``poisson``, ``bini``, a
        plugin's), its options as keyword arguments checked like ``--integrator-set``; through the
        capture's camera when it is perspective. Returns a ``pstoolkit.surface.Surface``: ``depth``
        (H, W) float64, z towards the camera (frame pixels for an orthographic capture, up to scale
        for a perspective one), NaN outside its ``mask``. UserError for an unknown integrator or
        option, or when no pixel was solved."""
        from pstoolkit.surface.outputs import camera_of  # deferred: the surface outputs load OpenCV and trimesh

        entry = get_registries().integrators.get(integrator)
        parsed = entry.parse_options(assignments(entry, options))
        if not self.mask.any():
            raise UserError(f"solver {self.solver!r} solved no pixel: there is no surface to integrate")
        return entry.obj().integrate(self.normal, self.mask, parsed, camera=camera_of(self.calibration))

    def write(self, folder: str | os.PathLike[str], *, name: str | None = None, obj: str | None = None, error_max_deg: float = 30.0) -> Path:
        """Write the result folder ``pstoolkit run`` writes (``normal.npy``/``.png``, each map as
        ``<map>.npy``/``.png``, ``error.npy``/``.png`` with ground truth, ``result.json`` recording
        the capture's path and checksum) to ``folder``, replacing it as a unit as ``run`` does; returns
        it as a Path. ``name`` is the result's name (default the solver's), ``obj`` the object's
        (default the capture's file stem), ``error_max_deg`` the top of ``error.png``'s scale in
        degrees. Add a surface with ``pstoolkit integrate FOLDER``.

        UserError for a capture made in memory (``result.json`` names the capture file: write it with
        ``psfmt.write`` and solve that), an ``error_max_deg`` outside (0, 180], or a ``folder`` that is a
        file or holds other files; PluginError for a malformed solver map, as ``pstoolkit run`` gives."""
        from pstoolkit.solve.results import SolvedCapture, check_error_max, prepare_maps, result_folder, result_summary, write_result_folder  # deferred: OpenCV

        if self.capture_path is None:
            raise UserError("the capture was made in memory: a result folder names its capture file (write it with psfmt.write and solve that)")
        check_error_max(error_max_deg, "error_max_deg")
        out = Path(folder)
        maps = prepare_maps(self.maps, self.mask, f"plugin {self.entry.plugin!r}: solver {self.solver!r}")
        solved = SolvedCapture(self.normal, self.mask, maps, self.score, self.seconds, self.data_rate, self.capture_kind, self.diagnostics)
        summary = result_summary(
            solved, entry=self.entry, name=name or self.solver, obj=obj or self.capture_path.stem, capture=self.capture_path,
            device=self.device, options=self.options, error_max_deg=error_max_deg,
        )
        with result_folder(out) as partial:
            write_result_folder(partial, solved, summary)
        return out


def _solve_open(entry: Entry, capture: psfmt.Capture, options: dict[str, Any], device: str, progress: Progress) -> Solution:
    from pstoolkit.evaluation.scoring import score  # deferred: keeps `import pstoolkit` to the plugin system

    result, seconds = run_solver(entry, capture, options, device=device, progress=progress)
    normal = np.where(result.mask[..., None], result.normal, np.float32(0.0))
    return Solution(
        normal=normal, mask=result.mask, maps=dict(result.maps), diagnostics=result.diagnostics, frames_used=result.frames_used,
        entry=entry, options=resolve_options(entry, options), device=device, seconds=seconds,
        data_rate=input_data_rate(entry, capture, result), score=score(normal, capture.ground_truth),
        capture_kind=capture.kind, capture_path=None if capture.path is None else Path(capture.path).absolute(),
        calibration=capture.calibration,
    )


def solve_capture(
    capture: psfmt.Capture | str | os.PathLike[str],
    solver: str,
    /,
    *,
    device: str = "auto",
    progress: Progress | None = None,
    **options: Any,
) -> Solution:
    """Run a registered solver on a capture, as ``pstoolkit run CAPTURE --solver SOLVER --set …`` does.

    Parameters
    ----------
    capture
        A ``psfmt.Capture`` (read lazily with ``psfmt.read``, loaded, or made in memory; a lazy one
        must stay open until ``solve_capture`` returns) or the path of a capture file, read and verified as
        ``pstoolkit run`` reads it and closed before returning.
    solver
        The solver's registry name (``frameps``, ``eventps``, ``dualres``, a plugin's).
    device
        ``auto`` (CUDA when available), ``cpu`` or ``cuda``, as ``--device``.
    progress
        ``progress(fraction, message)`` called now and then with the share of the work done in
        [0, 1]; None reports nowhere.
    **options
        The solver's options by name (``robust=True``, ``frames=6``), the others at their defaults:
        each value is checked by the registry entry's typed options as ``--set key=value`` is, so
        ``frames=-1`` raises the UserError ``--set frames=-1`` raises.

    Returns
    -------
    Solution
        The solver's ``SolverResult`` with its seconds, options, data rate and score.

    Raises
    ------
    UserError
        An unknown solver or option, a bad option value (an int outside 64 bits too), a
        ``progress`` that is not callable, ``device`` not available, a capture that
        lacks what the solver needs; ``psfmt.FormatError`` for a capture file that does not read.
    """
    entry = get_registries().solvers.get(solver)
    parsed = entry.parse_options(assignments(entry, options))
    device = resolve_device(device)
    if progress is not None and not callable(progress):
        raise UserError(f"progress must be a function progress(fraction, message) or None, not {type(progress).__name__}")
    report = no_progress if progress is None else progress
    if isinstance(capture, psfmt.Capture):
        return _solve_open(entry, capture, parsed, device, report)
    if not isinstance(capture, (str, os.PathLike)):
        raise TypeError(f"capture must be a psfmt.Capture or the path of a capture file, not {type(capture).__name__}")
    with psfmt.read(capture, verify=True) as data:
        return _solve_open(entry, data, parsed, device, report)
