"""pstoolkit — the photometric-stereo core: plugins and registries, shared maths, simulator, CLI.

The package is split by job: ``plugin`` (hook specifications, the plugin manager, registries, typed
options), ``optics`` (light models, equivalent lights, light layouts, BRDFs), ``events`` (the event
rule and the EventPS relation), ``sim`` (scenes, renderer, event engines, the simulator), ``solve``
(the solver interface, result folders, batch runs), ``shadows`` (cast-shadow detectors),
``surface`` (normal integration), ``evaluation`` (scores, tables, the report), ``hardware``
(backends, calibration), ``io`` (normal maps, DiLiGenT folders, converters) and ``cli``.

The parts stand in layers, lowest first: ``errors``, ``version``, ``_shared``, ``grid``, ``plugin``,
``io``, ``optics``, ``events``, ``evaluation``, ``surface``, ``shadows``, ``solve``, ``hardware``,
``sim``, ``view``, this root, ``cli``. A module imports its own part or a lower one, never a higher
one, and no two modules import each other (``tests/test_layout.py`` reads the imports and checks).

A plugin imports what it needs from here: ``hookimpl`` to mark its hook functions, ``Option`` for
typed options, ``Registry`` for the registries its hooks receive, ``Solver``/``SolverResult`` and
``Progress`` for solvers, ``Converter`` for dataset converters, ``LightBackend`` and ``CameraSource``
for hardware, ``LightCalibration``/``LightFit`` for light calibrations, ``LightModel`` and the built-in light models, ``BRDF``/``FitParam`` for reflectance
models, ``ShadowDetector`` and its evidence and mask types for shadow detectors, ``UserError`` for
one-line errors, and the units and constants (``US_PER_S``, ``GREY_WEIGHTS``). Importing the
package loads neither torch nor numba: ``BRDF`` and ``FitParam`` (torch) load on first use.

From Python, ``pstoolkit.solve_capture(capture, "frameps", robust=True)`` runs a registered solver on a
capture (a ``psfmt.Capture`` or a path) and returns a ``Solution`` (``pstoolkit.solve.api``).
"""

from __future__ import annotations

from typing import Any

from pstoolkit._shared.progress import Progress, no_progress
from pstoolkit.errors import UserError
from pstoolkit.hardware.backend import CameraSource, LightBackend
from pstoolkit.hardware.lightcal import LightCalibration, LightFit
from pstoolkit.io.converter import Converter
from pstoolkit.optics.grey import GREY_WEIGHTS
from pstoolkit.optics.lights import US_PER_S, LightModel, NearRingLight, RingLight, SampledLight, build_light_model
from pstoolkit.plugin.manager import get_registries
from pstoolkit.plugin.options import Option
from pstoolkit.plugin.registry import Registry
from pstoolkit.plugin.spec import hookimpl
from pstoolkit.shadows import ShadowDetector, ShadowEvidence, ShadowIntervals, ShadowMask
from pstoolkit.solve.api import Solution, solve_capture
from pstoolkit.solve.base import Solver, SolverResult
from pstoolkit.version import __version__

_TORCH_NAMES = {"BRDF": "pstoolkit.optics.brdf", "FitParam": "pstoolkit.optics.brdf"}


def __getattr__(name: str) -> Any:
    # PEP 562: the torch-backed names load on first use so that `import pstoolkit` stays light
    if name in _TORCH_NAMES:
        import importlib

        return getattr(importlib.import_module(_TORCH_NAMES[name]), name)
    raise AttributeError(f"module 'pstoolkit' has no attribute {name!r}")


__all__ = [
    "BRDF", "GREY_WEIGHTS", "US_PER_S", "CameraSource", "Converter", "FitParam", "LightBackend",
    "LightCalibration", "LightFit", "LightModel",
    "NearRingLight", "Option", "Progress", "Registry", "RingLight", "SampledLight", "ShadowDetector", "ShadowEvidence",
    "ShadowIntervals", "ShadowMask", "Solution", "Solver", "SolverResult", "UserError", "__version__", "build_light_model",
    "get_registries", "hookimpl", "no_progress", "solve_capture",
]
