"""The ``pstoolkit_register_integrators`` hook: a third party's integrator (the example of
docs/hooks.md) is registered, attributed, listed by ``pstoolkit plugins`` and integrates."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pstoolkit.cli import main
from pstoolkit.evaluation.metrics import depth_error
from pstoolkit.plugin import manager as plugins
from pstoolkit.plugin.manager import get_registries, load_failures
from pstoolkit.surface.shapes import sphere
from pstoolkit.testing import fake_distribution

SMOOTHED = """
    import numpy as np
    import scipy.ndimage

    from pstoolkit import Option, hookimpl
    from pstoolkit.surface import Integrator
    from pstoolkit.surface.base import checked_inputs
    from pstoolkit.surface.poisson import PoissonIntegrator

    class SmoothedPoisson(Integrator):
        name = "smoothed-poisson"
        summary = "poisson on normals blurred inside the mask first, for noisy maps"
        options = (Option("sigma", float, 1.0, "Gaussian blur, pixels", minimum=0.0),)

        def integrate(self, normal, mask, options, camera=None):
            normal, mask = checked_inputs(normal, mask)
            sigma = options["sigma"]
            inside = scipy.ndimage.gaussian_filter(mask.astype(float), sigma)  # blur only the mask's normals
            blurred = scipy.ndimage.gaussian_filter(normal, (sigma, sigma, 0)) / np.maximum(inside, 1e-12)[..., None]
            return PoissonIntegrator().integrate(blurred, mask, {}, camera)

    @hookimpl
    def pstoolkit_register_integrators(registry):
        registry.register(SmoothedPoisson)
    """


def test_hook_pstoolkit_register_integrators(
    pstoolkit_plugins_alone: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    fake_distribution(tmp_path, "pskfake-smooth", "2.0", {"smooth": "pskfake_smooth"}, {"pskfake_smooth": SMOOTHED})
    pstoolkit_plugins_alone.syspath_prepend(str(tmp_path))
    pstoolkit_plugins_alone.setenv(plugins.ALLOW_ENV, "smooth")
    entry = get_registries().integrators.get("smoothed-poisson")
    assert (entry.plugin, entry.kind) == ("smooth", "integrator")
    assert load_failures() == []
    truth = sphere(64, 28.0)
    surface = entry.obj().integrate(truth.normal, truth.mask, entry.parse_options(["sigma=0.5"]))
    assert depth_error(surface.depth, truth.depth, truth.mask).rmse < 0.01 * 56.0  # blurring costs a little at the rim
    assert np.isnan(surface.depth[~truth.mask]).all()
    assert main(["plugins"]) == 0
    out = capsys.readouterr().out
    assert "smooth 2.0  (pskfake_smooth, entry point)\n  integrators:\n    smoothed-poisson  poisson on normals blurred" in out
    assert "--set sigma (float, default 1.0): Gaussian blur, pixels" in out
