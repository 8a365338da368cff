"""The stages a GPU runs as torch copies of the host's code (``devices.on_host``: the closed form's
iteration, the surface's integration and shadow sweep, the runs and edges of its shadows, the lookups
of the masks the fit takes, the bounce's work over the pixels), run end to end through torch on the CPU,
give the host's result: CI has no GPU, so this is where the copies meet the rest of the pipeline."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import psfmt
import pstoolkit.surface.integrate_device as integrate_device
from pstoolkit._shared import devices
from pstoolkit.evaluation.metrics import angular_error_deg
from pstoolkit.optics.shadow_sweep import ShadowCaster
from pstoolkit.optics.shadow_sweep_device import DeviceCaster
from pstoolkit.plugin.manager import get_registries
from pstoolkit.shadows.base import ShadowMask
from pstoolkit.shadows.device_tracking import DeviceEdgeTracker, DeviceRunCollector
from pstoolkit.shadows.edge_tracking import EdgeTracker
from pstoolkit.shadows.intervals import RunCollector
from pstoolkit.shadows.table_device import DeviceShadowMask
from pstoolkit.solve.base import SolverResult, run_solver
from pstoolkit_dualres import closed_form
from pstoolkit_dualres.bounce import Bounce
from pstoolkit_dualres.bounce_device import DeviceBounce


def _solve(capture: psfmt.Capture) -> SolverResult:
    entry = get_registries().solvers.get("dualres")
    return run_solver(entry, capture, entry.parse_options(["epochs=40"]))[0]


def test_the_device_path_on_the_cpu_gives_the_hosts_normals(blobs_48: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    capture = psfmt.load(blobs_48)
    host = _solve(capture)
    used = []
    for owner, name in ((closed_form, "device_fixed_point"), (integrate_device, "integrate_normals_on"),
                        (DeviceCaster, "margins"), (DeviceRunCollector, "intervals"), (DeviceEdgeTracker, "edges"),
                        (EdgeTracker, "feed"), (ShadowCaster, "margins"), (DeviceShadowMask, "shadowed_us"),
                        (DeviceShadowMask, "contains_grid"), (ShadowMask, "shadowed_us"), (ShadowMask, "contains"),
                        (ShadowMask, "contains_grid"), (ShadowMask, "shadowed_grid"), (DeviceBounce, "at"), (Bounce, "at")):
        real = getattr(owner, name)
        monkeypatch.setattr(owner, name, lambda *args, real=real, name=f"{owner.__name__}.{name}", **kwargs:
                            used.append(name) or real(*args, **kwargs))
    fed: list[object] = []
    feed = RunCollector.feed
    monkeypatch.setattr(RunCollector, "feed", lambda self, block: fed.append(block) or feed(self, block))
    monkeypatch.setattr(devices, "on_host", lambda device: False)
    there = _solve(capture)
    # the start, its solve under the first mask; the first stage's surface and the bounce fit's
    assert used.count("pstoolkit_dualres.closed_form.device_fixed_point") == 2
    assert used.count("pstoolkit.surface.integrate_device.integrate_normals_on") == 2
    # every sweep, its runs and edges on the device's side, and the seen edges' runs too: no host collector is fed
    assert {"DeviceCaster.margins", "DeviceRunCollector.intervals", "DeviceEdgeTracker.edges"} <= set(used)
    assert not {"EdgeTracker.feed", "ShadowCaster.margins"} & set(used)
    # every mask the fit and the closed form take is looked up on the device's side
    assert used.count("DeviceShadowMask.shadowed_us") >= 3 and "DeviceShadowMask.contains_grid" in used
    assert not [name for name in used if name.startswith("ShadowMask.")]
    # the bounce the fit tries is read back at the pairs' taps there
    assert "DeviceBounce.at" in used and "Bounce.at" not in used
    assert fed == []
    truth = capture.ground_truth
    assert np.array_equal(host.mask, there.mask)
    mae = [float(angular_error_deg(r.normal, truth.normal, truth.mask)[truth.mask].mean()) for r in (host, there)]
    assert abs(mae[1] - mae[0]) <= 0.002  # measured equal to 1e-15
    apart = angular_error_deg(there.normal, host.normal, host.mask)[host.mask]
    assert np.percentile(apart, 90) <= 0.01  # measured 9e-7°: the sweeps' masks are the same
    assert there.diagnostics["stages"][0]["shadow_intervals"] == host.diagnostics["stages"][0]["shadow_intervals"]
