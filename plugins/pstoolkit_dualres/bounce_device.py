"""The bounce's work over the frame pixels on a torch device, for a fit that is not on the CPU
(``interreflection.remove_bounce``): each cell's mean direct irradiance at every phase
(``bounce.Cells.direct``), the bounce read back at phases and pixels (``bounce.Bounce``), and from it
the frames' offsets and the event pairs' bounce irradiance (``interreflection.frame_offsets`` and
``event_offsets``). The sum over the cells between (``bounce._bounce``, at most ``WORK_SIDE``² cells)
stays the host's compiled kernel: its inputs and its result are a few MB.

Each is the host's float64 expression; the sums over a cell's pixels and a pixel's samples are taken
by ``index_add_``, in another order than the host's, so the results equal the host's to rounding (a
test holds them to it). Work over pixels, samples or pairs is split in batches of at most
``BATCH_BYTES`` (or a quarter of a GPU's free memory).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from pstoolkit._shared import devices
from pstoolkit_dualres.bounce import Bounce, Cells

if TYPE_CHECKING:
    from pstoolkit_dualres.problem import EventTerms, FrameTerms

# Device memory a batch of phases, samples or pairs may take, at most (``devices.memory_budget``).
BATCH_BYTES = 1 << 30


def _rows_per_batch(device: torch.device, row_bytes: int) -> int:
    return max(1, devices.memory_budget(device, BATCH_BYTES) // max(row_bytes, 1))


def cell_direct_there(cells: Cells, normal: Tensor, lit: Tensor, directions: np.ndarray) -> np.ndarray:
    """``cells.direct`` of the (P, 3) float64 ``normal`` and (T, P) bool ``lit`` on their device, for the
    (T, 3) unit ``directions``: (Hc, Wc, T) float64 on the host."""
    device = normal.device
    cell = torch.as_tensor(cells.cell, dtype=torch.int64, device=device)
    n_cells = cells.shape[0] * cells.shape[1]
    count = torch.zeros(n_cells, dtype=torch.float64, device=device).index_add_(
        0, cell, torch.ones(cell.numel(), dtype=torch.float64, device=device))
    light = torch.as_tensor(np.asarray(directions, dtype=np.float64), device=device)
    out = torch.empty((n_cells, len(light)), dtype=torch.float64, device=device)
    step = _rows_per_batch(device, 16 * max(cell.numel(), 1))
    for first in range(0, len(light), step):
        part = slice(first, first + step)
        plane = torch.clamp(normal @ light[part].T, min=0.0) * lit[part].T  # (P, n)
        out[:, part] = torch.zeros((n_cells, plane.shape[1]), dtype=torch.float64, device=device).index_add_(0, cell, plane)
    out /= torch.clamp(count, min=1e-12)[:, None]
    return out.reshape(*cells.shape, len(light)).cpu().numpy()


@dataclass
class DeviceBounce:
    """``Bounce`` on a torch device: ``value`` (T, C, 3) float32 and ``cell`` (P,) int64 there."""

    value: Tensor
    cell: Tensor
    period_us: float

    @classmethod
    def of(cls, bounce: Bounce, device: torch.device) -> DeviceBounce:
        return cls(torch.as_tensor(bounce.value, device=device), torch.as_tensor(bounce.cell, dtype=torch.int64, device=device),
                   float(bounce.period_us))

    def _bracket(self, phase_us: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        t = self.value.shape[0]
        pos = torch.remainder(phase_us / self.period_us * t - 0.5, t)
        floor = torch.floor(pos)
        lo = floor.to(torch.int64)
        return lo, (lo + 1) % t, pos - floor

    def at(self, phase_us: Tensor, rows: Tensor) -> Tensor:
        """``Bounce.at``: (N, 3) float64 at the pixels ``rows`` (N,) and float64 phases ``phase_us`` (N,)."""
        lo, hi, frac = self._bracket(phase_us)
        cell = self.cell[rows]
        return self.value[lo, cell] * (1.0 - frac[:, None]) + self.value[hi, cell] * frac[:, None]

    def everywhere(self, phase_us: float) -> Tensor:
        """``Bounce.everywhere``: (P, 3) float64 at every masked pixel at one phase."""
        lo, hi, frac = self._bracket(torch.tensor([phase_us], dtype=torch.float64, device=self.value.device))
        return (self.value[lo] * (1.0 - frac[:, None, None]) + self.value[hi] * frac[:, None, None])[0][self.cell]


def frame_offsets_there(frames: FrameTerms, bounce: DeviceBounce, albedo: Tensor, t0_us: float, period_us: float) -> Tensor:
    """``interreflection.frame_offsets`` on the device of the (P, 3) float64 ``albedo``: (K·P, 3) float64
    there, from the frame samples' sources moved there (``FrameTerms.source_there``)."""
    k, p = frames.count, albedo.shape[0]
    device = albedo.device
    if frames.shared_weight is not None:
        weight = frames.shared_weight.detach().to(torch.float64)  # (K·S, 3), frame-major
        per_frame = len(weight) // k
        light = torch.zeros((k, p, 3), dtype=torch.float64, device=device)
        for sample, t_us in enumerate(frames.source["shared_t"]):
            light[sample // per_frame] += bounce.everywhere(float(np.mod(t_us - t0_us, period_us))) * weight[sample]
        return (albedo[None] * light).reshape(k * p, 3)
    src = frames.source_there
    out = torch.zeros((k * p, 3), dtype=torch.float64, device=device)
    step = _rows_per_batch(device, 160)
    for first in range(0, frames.sample_pixel.numel(), step):
        part = slice(first, first + step)
        pixel = frames.sample_pixel[part]
        phase = torch.remainder(src["sample_t"][part] - t0_us, period_us)
        out.index_add_(0, frames.sample_group[part], albedo[pixel] * bounce.at(phase, pixel) * src["sample_weight"][part])
    return out


def event_offsets_there(events: EventTerms, bounce: DeviceBounce, albedo: Tensor, t0_us: float, period_us: float
                        ) -> tuple[Tensor, Tensor]:
    """``interreflection.event_offsets`` on the device of the (P, 3) float64 ``albedo``: (E,) float64 each
    there, from the pairs' sources moved there (``EventTerms.source_there``)."""
    src = events.source_there
    taps, area = events.taps, src["area"]
    count, fan = taps.shape
    step = _rows_per_batch(albedo.device, 200 * fan)
    out = []
    for key, grey in (("t_us", events.grey_now), ("t_ref_us", events.grey_ref)):
        phase = torch.remainder(src[key] - t0_us, period_us)
        value = torch.empty(count, dtype=torch.float64, device=albedo.device)
        for first in range(0, count, step):
            part = slice(first, first + step)
            tapped = taps[part]
            light = bounce.at(phase[part].repeat_interleave(fan), tapped.reshape(-1)).reshape(-1, fan, 3)
            shaded = (albedo[tapped] * light * grey[part, None, :].to(torch.float64)).sum(dim=-1)
            value[part] = (shaded * area[part]).sum(dim=-1)
        out.append(value)
    return out[0], out[1]
