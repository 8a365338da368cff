"""First-party plugin: the ``mitsuba`` renderer (``pstoolkit simulate SCENE --renderer mitsuba``) and the
``mesh`` scene (a mesh file, ``--source FILE``), path-traced
captures through Mitsuba 3 — an independent check of the solvers on images the toolkit's own model
did not make (``docs/renderers.md``). Needs the extra: ``pip install 'pstoolkit[mitsuba]'``.

    from pstoolkit_mitsuba import render_scene
    render_scene("blobs", size=64, bsdf="roughplastic", capture="blobs-pt.h5", diligent="blobsPNG")

Mitsuba is imported when a scene is rendered, so the plugin registers (and ``pstoolkit plugins``
lists it) without the extra installed.
"""

from __future__ import annotations

from typing import Any

from pstoolkit import Registry, hookimpl

__all__ = ["render_scene", "scene_config"]


def __getattr__(name: str) -> Any:
    # PEP 562: the API loads the simulator (torch, numba) on first use, not when the plugin registers
    if name in __all__:
        from pstoolkit_mitsuba import api

        return getattr(api, name)
    raise AttributeError(f"module 'pstoolkit_mitsuba' has no attribute {name!r}")


@hookimpl
def pstoolkit_register_scenes(registry: Registry) -> None:
    from pstoolkit_mitsuba.meshscene import MeshScene

    registry.register(MeshScene)


@hookimpl
def pstoolkit_register_renderers(registry: Registry) -> None:
    from pstoolkit_mitsuba.renderer import MitsubaRenderer

    registry.register(MitsubaRenderer)
