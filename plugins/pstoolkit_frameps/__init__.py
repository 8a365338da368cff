"""First-party plugin: the ``frameps`` least-squares photometric-stereo solver (Woodham 1980).

Found through the ``pstoolkit`` entry-point group like any third-party plugin; the solver module is
imported inside the hook so listing plugins stays cheap.
"""

from __future__ import annotations

from pstoolkit import Registry, hookimpl


@hookimpl
def pstoolkit_register_solvers(registry: Registry) -> None:
    from pstoolkit_frameps.solver import FramePS

    registry.register(FramePS)
