"""From normals to surfaces: normal integration, a registry kind (``integrators``) like the solvers.

``pstoolkit.surface.base`` holds the contract — ``Camera`` (pinhole intrinsics), ``Surface`` (the
depth map an integrator returns, its units and frame), ``Integrator`` (the base class registered
through ``pstoolkit_register_integrators``) and ``points`` (the 3-D point of each pixel, for meshes).
Built in (registered by the ``core`` plugin):

- ``poisson``: least squares on the mask (``pstoolkit.surface.poisson``), orthographic or perspective;
- ``bini``: bilateral normal integration, which keeps depth steps (``pstoolkit.surface.bini``).

``integrate_normals`` (``pstoolkit.surface.integrate``) is the orthographic least-squares solve the
shadow detectors use directly; ``pstoolkit.surface.shapes`` has analytic test surfaces.
"""

from __future__ import annotations

from pstoolkit.surface.base import Camera, Integrator, Surface, points
from pstoolkit.surface.integrate import integrate_normals, surface_gradients

__all__ = ["Camera", "Integrator", "Surface", "integrate_normals", "points", "surface_gradients"]
