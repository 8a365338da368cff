"""The estimated surface's cast shadows on a time grid: the solver's normals integrated into a height
map (``surface_height``), marched towards the light a block of directions at a time with the
simulator's shadow sweep (``surface_shadow_blocks``). Shared by the ``geometry`` and ``fused`` detectors
and the height-scale calibration (``height_scale``)."""

from __future__ import annotations

from collections.abc import Iterator
from typing import TYPE_CHECKING

import numpy as np

from pstoolkit._shared import devices
from pstoolkit.shadows.base import ShadowEvidence
from pstoolkit.shadows.intervals import grid_times
from pstoolkit.shadows.sweep_kernels import shadowed_columns

if TYPE_CHECKING:
    from torch import Tensor

# Light directions swept at once: bounds the (chunk, H, W) float32 margins held in memory.
SWEEP_CHUNK = 32
# On a device, the margins of a block of directions may take this much of its memory at most
# (``devices.memory_budget``; the sweep's own arrays are bounded apart, ``shadow_sweep_device.BATCH_BYTES``).
DEVICE_BLOCK_BYTES = 1 << 28


def integrated_height(evidence: ShadowEvidence) -> np.ndarray:
    """(H, W) float64 height map (pixels) of the surface ``evidence.normal`` (not None), integrated
    over ``evidence.mask`` (``pstoolkit.surface.integrate_normals``; on the evidence's torch device
    when that is not the CPU, ``integrate_device``), 0 outside it. Once per surface
    (``ShadowEvidence.of_surface``): the detectors' sweeps and a solver's model of the same surface
    (dualres's inter-reflection) share one solve, the costliest step of a detection at 1024². The map
    is read-only."""
    from pstoolkit.surface import integrate_normals

    def integrate() -> np.ndarray:
        normal, mask = np.asarray(evidence.normal, dtype=np.float64), np.asarray(evidence.mask, dtype=bool)
        if devices.on_host(evidence.device):
            height = integrate_normals(normal, mask)
        else:
            from pstoolkit.surface.integrate_device import integrate_normals_on  # deferred: torch

            height = integrate_normals_on(normal, mask, evidence.device)
        height.flags.writeable = False
        return height

    return evidence.of_surface(("integrated_height",), integrate)


def surface_height(evidence: ShadowEvidence) -> np.ndarray:
    """(H, W) float32 ``integrated_height``: the precision the sweeps march in."""
    return integrated_height(evidence).astype(np.float32)


def surface_shadow_blocks(evidence: ShadowEvidence, height: np.ndarray, time_steps: int, margin_px: float
                          ) -> Iterator[np.ndarray | Tensor]:
    """Cast shadows of the surface of ``height`` (``surface_height``) at the bin centres of
    ``intervals.grid_times`` from ``evidence.t0_us``, as blocks of times in order: (n, P) bool each,
    P the masked frame pixels in flat order. A block is a view of a buffer the next one overwrites:
    use it (or copy it) before asking for the next. The whole (time_steps, P) map never exists (0.75 GB
    at 1024² pixels and 720 steps). On the evidence's torch device when that is not the CPU
    (``shadow_sweep_device``, the same margins), where the blocks stay: torch tensors of up to
    DEVICE_BLOCK_BYTES of margins, for ``device_tracking``'s collectors."""
    mask = np.asarray(evidence.mask, dtype=bool)
    directions = evidence.light.evaluate(evidence.t0_us + grid_times(evidence.period_us, time_steps))[0]
    inside = np.flatnonzero(mask.ravel())
    if devices.on_host(evidence.device):
        yield from _host_blocks(height, mask, inside, directions, margin_px)
    else:
        yield from _device_blocks(height, mask, inside, directions, margin_px, evidence.device)


def _host_blocks(height: np.ndarray, mask: np.ndarray, inside: np.ndarray, directions: np.ndarray, margin_px: float
                 ) -> Iterator[np.ndarray]:
    """``surface_shadow_blocks`` with the compiled sweep, SWEEP_CHUNK directions at a time."""
    # deferred: the sweep is compiled with numba, which `pstoolkit plugins` need not load
    from pstoolkit.optics.shadow_sweep import ShadowCaster

    time_steps = len(directions)
    # one caster (the height map in its four sweep orientations) and one set of buffers for all blocks
    caster = ShadowCaster(height, mask)
    margin = np.empty((min(SWEEP_CHUNK, time_steps), *mask.shape), dtype=np.float32)
    out = np.empty((len(margin), inside.size), dtype=bool)
    for start in range(0, time_steps, SWEEP_CHUNK):
        block = directions[start : start + SWEEP_CHUNK]
        n = len(block)
        caster.margins(block, margin[:n])
        shadowed_columns(margin[:n].reshape(n, -1), margin_px, inside, out[:n])
        yield out[:n]


def _device_blocks(height: np.ndarray, mask: np.ndarray, inside: np.ndarray, directions: np.ndarray, margin_px: float,
                   device: str) -> Iterator[Tensor]:
    """``surface_shadow_blocks`` swept on the torch ``device``, the blocks left there."""
    import torch  # deferred: only a solver on a device sweeps there

    from pstoolkit.optics.shadow_sweep_device import DeviceCaster

    caster = DeviceCaster(height, mask, device)
    columns = torch.as_tensor(inside, device=caster.device)
    chunk = max(1, devices.memory_budget(caster.device, DEVICE_BLOCK_BYTES) // max(4 * mask.size, 1))
    for start in range(0, len(directions), chunk):
        margin = caster.margins(directions[start : start + chunk])
        yield margin.reshape(len(margin), -1)[:, columns] > float(np.float32(margin_px))
