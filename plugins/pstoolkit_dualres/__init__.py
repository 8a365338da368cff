"""First-party plugin: the `dualres` DualResPS solver (frames + events, neural inverse rendering).

The solver module (and torch) is imported inside the hook so listing plugins stays cheap.
"""

from __future__ import annotations

from pstoolkit import Registry, hookimpl


@hookimpl
def pstoolkit_register_solvers(registry: Registry) -> None:
    from pstoolkit_dualres.solver import DualRes

    registry.register(DualRes)
