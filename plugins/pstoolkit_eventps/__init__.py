"""First-party plugin: the ``eventps`` solver, the optimisation version of EventPS (Yu et al., CVPR 2024).

Found through the ``pstoolkit`` entry-point group like any third-party plugin; the solver module is
imported inside the hook so listing plugins stays cheap.
"""

from __future__ import annotations

from pstoolkit import Registry, hookimpl


@hookimpl
def pstoolkit_register_solvers(registry: Registry) -> None:
    from pstoolkit_eventps.solver import EventPS

    registry.register(EventPS)
