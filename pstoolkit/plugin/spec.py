"""The hooks a pstoolkit plugin may implement, one docstring each (``docs/hooks.md`` has examples).

A plugin is a module (or object) with functions marked ``@pstoolkit.hookimpl`` whose names are the
hooks below. The register hooks hand the plugin a ``Registry``; the plugin calls
``registry.register(cls)`` for each thing it provides (the tox 4 pattern), so every entry is
attributed to the plugin that registered it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import pluggy

if TYPE_CHECKING:
    import typer

    from pstoolkit.plugin.registry import Registry

PROJECT = "pstoolkit"

hookspec = pluggy.HookspecMarker(PROJECT)
hookimpl = pluggy.HookimplMarker(PROJECT)


@hookspec
def pstoolkit_register_light_models(registry: Registry) -> None:
    """Register light models: how light direction and intensity vary over time (a ring of LEDs,
    sampled directions …). ``LightSpec.model`` in a capture names an entry of this registry."""


@hookspec
def pstoolkit_register_shadow_detectors(registry: Registry) -> None:
    """Register shadow detectors (subclasses of ``pstoolkit.shadows.ShadowDetector``): rules that
    mark when each pixel lies in a cast shadow, from a capture's ``ShadowEvidence``, so a solver
    leaves those observations out; solvers take them by name (``dualres --set shadow_detector=NAME``)."""


@hookspec
def pstoolkit_register_brdfs(registry: Registry) -> None:
    """Register reflectance models (subclasses of ``pstoolkit.optics.brdf.BRDF``) that the simulator renders
    with and solvers fit (``dualres --set brdf=NAME``), each saying how its maps are fitted (``fit``)."""


@hookspec
def pstoolkit_register_solvers(registry: Registry) -> None:
    """Register photometric-stereo solvers (subclasses of ``pstoolkit.solve.base.Solver``); each
    becomes a choice of ``pstoolkit run --solver NAME``."""


@hookspec
def pstoolkit_register_backends(registry: Registry) -> None:
    """Register hardware backends: drivers for light rigs and cameras that record captures."""


@hookspec
def pstoolkit_register_converters(registry: Registry) -> None:
    """Register converters that turn other formats (datasets, event files) into hybrid captures;
    each becomes a choice of ``pstoolkit convert FORMAT``."""


@hookspec
def pstoolkit_register_scenes(registry: Registry) -> None:
    """Register synthetic scenes (geometry and materials) that ``pstoolkit simulate SCENE`` renders."""


@hookspec
def pstoolkit_register_integrators(registry: Registry) -> None:
    """Register normal integrators (subclasses of ``pstoolkit.surface.base.Integrator``) that turn a
    normal map into a depth map, orthographic or through a pinhole camera; callers take them by name,
    so methods can be swapped like solvers."""


@hookspec
def pstoolkit_register_renderers(registry: Registry) -> None:
    """Register independent renderers (subclasses of ``pstoolkit.sim.renderers.SceneRenderer``) that
    draw a scene's images under any light (a path tracer, say); each becomes a choice of
    ``pstoolkit simulate SCENE --renderer NAME``, whose captures are then assembled from their key
    images (``pstoolkit.sim.keyed``)."""


@hookspec
def pstoolkit_register_light_calibrations(registry: Registry) -> None:
    """Register light calibrations (subclasses of ``pstoolkit.hardware.lightcal.LightCalibration``):
    ways to measure a rig's light model from a recording of a target (a chrome sphere …); each
    becomes a choice of ``pstoolkit calibrate lights SOURCE --method NAME``."""


@hookspec
def pstoolkit_add_commands(app: typer.Typer) -> None:
    """Add commands to the ``pstoolkit`` command line: decorate functions with ``@app.command()``.
    Called once, when the ``pstoolkit`` command starts (``pstoolkit.cli.main``)."""
