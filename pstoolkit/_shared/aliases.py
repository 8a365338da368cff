"""The module paths pstoolkit had before it was split into subpackages (``pstoolkit.render`` →
``pstoolkit.sim.render`` …, ``pstoolkit.shadows.profile`` → ``pstoolkit.shadows.period_profile``),
answered with the moved module itself until the release after 0.2: an import finder, so the old
names need no files and patching either name patches the one module."""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import importlib.util
import sys
from types import ModuleType

MOVED: dict[str, str] = {
    "pstoolkit.allocator": "pstoolkit._shared.allocator",
    "pstoolkit.backend": "pstoolkit.hardware.backend",
    "pstoolkit.batch": "pstoolkit.solve.batch",
    "pstoolkit.brdf": "pstoolkit.optics.brdf",
    "pstoolkit.calibrate": "pstoolkit.hardware.calibrate",
    "pstoolkit.converter": "pstoolkit.io.converter",
    "pstoolkit.demo": "pstoolkit.sim.demo",
    "pstoolkit.diligentexport": "pstoolkit.io.diligent_export",
    "pstoolkit.diligentlayout": "pstoolkit.io.diligent_layout",
    "pstoolkit.equivalent": "pstoolkit.optics.equivalent",
    "pstoolkit.esim": "pstoolkit.sim.esim",
    "pstoolkit.eventfill": "pstoolkit.events.fill",
    "pstoolkit.eventkernel": "pstoolkit.events.relation_kernel",
    "pstoolkit.eventmodel": "pstoolkit.events.rule",
    "pstoolkit.eventnormals": "pstoolkit.events.relation",
    "pstoolkit.eventps": "pstoolkit.events.eventps",
    "pstoolkit.folders": "pstoolkit.io.folders",
    "pstoolkit.hookspecs": "pstoolkit.plugin.spec",
    "pstoolkit.layouts": "pstoolkit.optics.layouts",
    "pstoolkit.lights": "pstoolkit.optics.lights",
    "pstoolkit.markup": "pstoolkit.evaluation.markup",
    "pstoolkit.metrics": "pstoolkit.evaluation.metrics",
    "pstoolkit.normalmap": "pstoolkit.io.normalmap",
    "pstoolkit.options": "pstoolkit.plugin.options",
    "pstoolkit.outputs": "pstoolkit.solve.results",
    "pstoolkit.plugins": "pstoolkit.plugin.manager",
    "pstoolkit.registry": "pstoolkit.plugin.registry",
    "pstoolkit.render": "pstoolkit.sim.render",
    "pstoolkit.report": "pstoolkit.evaluation.report",
    "pstoolkit.scenes": "pstoolkit.sim.scenes",
    "pstoolkit.simkernel": "pstoolkit.sim.ring_engine",
    "pstoolkit.simulator": "pstoolkit.sim.simulator",
    "pstoolkit.solver": "pstoolkit.solve.base",
    "pstoolkit.worksharing": "pstoolkit._shared.worksharing",
    "pstoolkit.shadows.profile": "pstoolkit.shadows.period_profile",
}


class _Alias(importlib.abc.Loader):
    """Loads an old name as the module it moved to, keeping that module's own spec."""

    def __init__(self, target: str) -> None:
        self.target = target
        self.own_spec: importlib.machinery.ModuleSpec | None = None

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> ModuleType:
        module = importlib.import_module(self.target)
        self.own_spec = module.__spec__
        return module

    def exec_module(self, module: ModuleType) -> None:
        # the import system has just stamped the alias's spec on the moved module; give it back its own
        module.__spec__ = self.own_spec


class _Finder(importlib.abc.MetaPathFinder):
    def find_spec(self, fullname: str, path: object = None, target: object = None) -> importlib.machinery.ModuleSpec | None:
        if fullname not in MOVED:
            return None
        return importlib.util.spec_from_loader(fullname, _Alias(MOVED[fullname]))


def install() -> None:
    """Answer the old names from now on (idempotent)."""
    if not any(isinstance(finder, _Finder) for finder in sys.meta_path):
        sys.meta_path.insert(0, _Finder())
