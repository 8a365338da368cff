"""The ``pstoolkit_register_renderers`` hook: a third party's renderer (the example of docs/hooks.md)
is registered, listed by ``pstoolkit plugins`` and drives ``pstoolkit simulate --renderer``, whose
capture is assembled from its key images (``pstoolkit.sim.keyed``) like the built-in one's."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import psfmt
from pstoolkit.cli import main
from pstoolkit.plugin import manager as plugins
from pstoolkit.plugin.manager import get_registries, load_failures
from pstoolkit.testing import fake_distribution

FLAT = """
    import numpy as np

    from pstoolkit import hookimpl, no_progress
    from pstoolkit.sim.renderers import Rendering, SceneRenderer

    class Flat(SceneRenderer):
        name = "flat"
        summary = "Lambertian shading without shadows, for checks"

        def prepare(self, maps, seed, **options):
            return FlatRendering(maps)

    class FlatRendering(Rendering):
        def __init__(self, maps):
            self.maps, self.mask, self.normal = maps, maps.mask, maps.normal

        def images(self, light, t_us, progress=no_progress):
            direction, intensity = light.evaluate(t_us)
            shading = np.clip(np.einsum("hwc,tc->thw", self.maps.normal, direction), 0, None)
            return (shading[..., None] * self.maps.albedo * intensity[:, None, None]).astype(np.float32)

    @hookimpl
    def pstoolkit_register_renderers(registry):
        registry.register(Flat)
    """


@pytest.fixture
def flat(pstoolkit_plugins_alone: pytest.MonkeyPatch, tmp_path: Path) -> None:
    fake_distribution(tmp_path, "pskfake-flat", "1.0", {"flat": "pskfake_flat"}, {"pskfake_flat": FLAT})
    pstoolkit_plugins_alone.syspath_prepend(str(tmp_path))
    pstoolkit_plugins_alone.setenv(plugins.ALLOW_ENV, "core,flat")


def test_hook_pstoolkit_register_renderers(flat: None, capsys: pytest.CaptureFixture[str]) -> None:
    entry = get_registries().renderers.get("flat")
    assert (entry.plugin, entry.kind) == ("flat", "renderer")
    assert load_failures() == []
    assert main(["plugins"]) == 0
    assert "flat 1.0  (pskfake_flat, entry point)\n  renderers:\n    flat  Lambertian shading without shadows" in capsys.readouterr().out


def test_a_renderers_capture_matches_the_own_engines(flat: None, tmp_path: Path) -> None:
    """A sphere (no cast shadows) under the Lambertian BRDF: the keyed capture's frames lie within a
    grey level of the own engine's exact integral, and it holds as many events within 3 %."""
    common = ["sphere", "--size", "32", "--set", "albedo=white", "--auto-gain", "peak", "-q"]
    assert main(["simulate", *common, "--renderer", "flat", "--key-step-deg", "2", "-o", str(tmp_path / "flat.h5")]) == 0
    assert main(["simulate", *common, "--brdf", "lambertian", "-o", str(tmp_path / "own.h5")]) == 0
    with psfmt.read(tmp_path / "flat.h5") as keyed, psfmt.read(tmp_path / "own.h5") as own:
        assert keyed.frames.count == own.frames.count == 3
        difference = np.abs(keyed.frames.data[:].astype(float) - own.frames.data[:].astype(float))
        assert difference.max() <= 1.0
        n_keyed, n_own = len(keyed.events), len(own.events)
        assert abs(n_keyed - n_own) <= 0.03 * n_own
        assert keyed.ground_truth.mask.sum() == own.ground_truth.mask.sum()
    report = psfmt.validate(tmp_path / "flat.h5")
    assert report.valid and not report.warnings


def test_an_unknown_renderer_is_one_line(flat: None, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["simulate", "sphere", "--size", "16", "--renderer", "nope", "-o", str(tmp_path / "x.h5")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "unknown renderer 'nope'" in err
    assert not (tmp_path / "x.h5").exists()
