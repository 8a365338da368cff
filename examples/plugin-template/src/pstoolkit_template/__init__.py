"""A template pstoolkit plugin: registers the ``flat`` solver, the ``static`` light model, the
``quiet`` shadow detector and the ``blinn-phong`` BRDF.

pstoolkit imports this module through the entry point declared in ``pyproject.toml`` and calls the
hooks below with its registries; copy the package and rename it to start your own plugin.
"""

from __future__ import annotations

from pstoolkit import Registry, hookimpl
from pstoolkit_template.flat import FlatSolver
from pstoolkit_template.phong import BlinnPhong
from pstoolkit_template.quiet import QuietDetector
from pstoolkit_template.static_light import StaticLight

__version__ = "0.1.0"


@hookimpl
def pstoolkit_register_solvers(registry: Registry) -> None:
    registry.register(FlatSolver)


@hookimpl
def pstoolkit_register_light_models(registry: Registry) -> None:
    registry.register(StaticLight)


@hookimpl
def pstoolkit_register_shadow_detectors(registry: Registry) -> None:
    registry.register(QuietDetector)


@hookimpl
def pstoolkit_register_brdfs(registry: Registry) -> None:
    registry.register(BlinnPhong)
