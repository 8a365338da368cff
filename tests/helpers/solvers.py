"""Shared builders, from test_run_cli.py."""

from __future__ import annotations

import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from pstoolkit.cli import main
from pstoolkit.plugin import manager as plugins
from pstoolkit.testing import fake_distribution

SIZE = 32


LIGHTS = 8


LSQ_PLUGIN = """
    import numpy as np

    from pstoolkit import Option, Solver, SolverResult, hookimpl
    from pstoolkit.errors import UserError


    class LeastSquares(Solver):
        name = "lsq"
        summary = "Woodham least squares under instantaneous lights"
        options = (Option("threshold", float, 0.02, "mask level", minimum=0.0),)
        needs = frozenset({"frames"})

        def solve(self, capture, options, progress):
            frames = capture.frames
            if not frames.has_instant_lights:
                raise UserError("solver 'lsq' needs instantaneous lights")
            images = frames.as_float()  # (K, H, W, 3)
            k, h, w, _ = images.shape
            lights = frames.light_direction  # (K, 3)
            pinv = np.linalg.pinv(lights)  # (3, K)
            rgb = np.einsum("ck,khwj->hwjc", pinv, images)  # b = ρ·n per channel
            grey = rgb.mean(axis=2)
            rho = np.linalg.norm(grey, axis=-1)
            normal = grey / np.maximum(rho, 1e-12)[..., None]
            mask = images.max(axis=(0, 3)) > options["threshold"]
            albedo = np.linalg.norm(rgb, axis=-1)
            shading = np.einsum("kc,hwc->khw", lights, grey)
            residual = np.sqrt(np.mean((shading - images.mean(axis=-1)) ** 2, axis=0))
            progress(1.0, "solved")
            return SolverResult(
                normal=normal, mask=mask, maps={"albedo": albedo, "residual": residual, "shading": shading}
            )


    class BadMap(LeastSquares):
        name = "badmap"
        summary = "returns a map under a name run uses itself"

        def solve(self, capture, options, progress):
            result = super().solve(capture, options, progress)
            result.maps["error"] = result.maps.pop("residual")
            return result


    class EventsOnly(LeastSquares):
        name = "evlsq"
        summary = "declares that it needs events"
        needs = frozenset({"events"})


    @hookimpl
    def pstoolkit_register_solvers(registry):
        for solver in (LeastSquares, BadMap, EventsOnly):
            registry.register(solver)
"""


@contextmanager
def lsq_plugin(monkeypatch: pytest.MonkeyPatch, root: Path) -> Iterator[None]:
    """Only the core plugin and the test solvers (installed under ``root``), and a private cache."""
    site = fake_distribution(root / "site", "pskfake-lsq", "1.0", {"lsq": "pskfake_lsq"}, {"pskfake_lsq": LSQ_PLUGIN})
    monkeypatch.syspath_prepend(str(site))
    monkeypatch.delenv(plugins.DISABLE_ENV, raising=False)
    monkeypatch.setattr(plugins, "BUILT_IN_DISTRIBUTION", "")  # the built-ins load only when named
    monkeypatch.setenv(plugins.ALLOW_ENV, "core,lsq")
    monkeypatch.setenv("XDG_CACHE_HOME", str(root / "cache"))
    plugins.reset()
    try:
        yield
    finally:
        plugins.reset()
        sys.modules.pop("pskfake_lsq", None)


def simulate_sphere(path: Path, *args: str) -> Path:
    """A Lambertian sphere under LIGHTS instantaneous ring lights, no shadows, no noise."""
    simulate = ["simulate", "sphere", "-o", str(path), "--size", str(SIZE), "--discrete-lights", str(LIGHTS)]
    assert main([*simulate, "--brdf", "lambertian", "--no-shadows", "--noise", "0", "--quiet", *args]) == 0
    return path
