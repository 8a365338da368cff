"""pstoolkit — the photometric-stereo core: plugins and registries, shared maths, simulator, CLI.

A plugin imports what it needs from here: ``hookimpl`` to mark its hook functions, ``Option`` for
typed options, ``Solver`` and ``SolverResult`` for solvers, ``Converter`` for dataset converters,
``LightBackend`` and ``CameraSource`` for hardware.
"""

from __future__ import annotations

__version__ = "0.1.0"

from pstoolkit.backend import CameraSource, LightBackend
from pstoolkit.converter import Converter
from pstoolkit.options import Option
from pstoolkit.plugins import get_registries, hookimpl
from pstoolkit.solver import Solver, SolverResult

__all__ = ["CameraSource", "Converter", "LightBackend", "Option", "Solver", "SolverResult", "__version__", "get_registries", "hookimpl"]
