"""First-party plugin that registers pstoolkit's built-in light models, shadow detectors, BRDFs, scenes,
normal integrators and light calibrations.

It is found through the ``pstoolkit`` entry-point group and uses the same hooks as a third-party
plugin. Imports sit inside the hooks, so a module that fails to import spoils only its own registry
and the command line starts without loading torch.
"""

from __future__ import annotations

from pstoolkit import Registry, hookimpl


@hookimpl
def pstoolkit_register_light_models(registry: Registry) -> None:
    from pstoolkit.optics.lights import NearRingLight, RingLight, SampledLight

    for model in (RingLight, SampledLight, NearRingLight):
        registry.register(model)


@hookimpl
def pstoolkit_register_shadow_detectors(registry: Registry) -> None:
    from pstoolkit.shadows.base import NoShadows
    from pstoolkit.shadows.fused import FusedDetector
    from pstoolkit.shadows.geometry import GeometryDetector
    from pstoolkit.shadows.silences import SilenceDetector
    from pstoolkit.shadows.spikes import SpikeDetector

    for detector in (NoShadows, SpikeDetector, SilenceDetector, GeometryDetector, FusedDetector):
        registry.register(detector)


@hookimpl
def pstoolkit_register_brdfs(registry: Registry) -> None:
    from pstoolkit.optics.brdf import BRDFS

    for brdf in BRDFS:
        registry.register(brdf)


@hookimpl
def pstoolkit_register_scenes(registry: Registry) -> None:
    from pstoolkit.sim.scenes import SCENES

    for scene in SCENES:
        registry.register(scene)


@hookimpl
def pstoolkit_register_integrators(registry: Registry) -> None:
    from pstoolkit.surface.bini import BiNIIntegrator
    from pstoolkit.surface.poisson import PoissonIntegrator

    for integrator in (PoissonIntegrator, BiNIIntegrator):
        registry.register(integrator)


@hookimpl
def pstoolkit_register_light_calibrations(registry: Registry) -> None:
    from pstoolkit.hardware.sphere_events import SphereEvents
    from pstoolkit.hardware.sphere_frames import SphereFrames

    for calibration in (SphereFrames, SphereEvents):
        registry.register(calibration)
