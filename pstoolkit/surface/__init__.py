"""From normals to surfaces: integration of normal maps into height maps."""

from __future__ import annotations

from pstoolkit.surface.integrate import integrate_normals, surface_gradients

__all__ = ["integrate_normals", "surface_gradients"]
