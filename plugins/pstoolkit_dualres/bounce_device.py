"""The bounce on a torch device, for a fit that is not on the CPU (``interreflection.remove_bounce``):
each cell's mean direct irradiance at every phase (``bounce.Cells.direct``), the sum over the cells
(``bounce._bounce``), the bounce read back at phases and pixels (``bounce.Bounce``), and from it the
frames' offsets and the event pairs' bounce irradiance (``interreflection.frame_offsets`` and
``event_offsets``). Only the pooling of the surface onto the cells (at most ``WORK_SIDE``² of them)
stays on the host.

Each is the host's float64 expression; the sums over a cell's pixels and a pixel's samples are taken
by ``index_add_``, in another order than the host's, so the results equal the host's to rounding (a
test holds them to it). The sum over the cells (``_sum_there``) takes each pair of cells the compiled
kernel takes, by the same float64 tests (facing, within the radius, the segment between them above the
height field, rounded to cells half to even), a batch of neighbour offsets at a time; the weights of
the pairs it keeps make a (C, C) matrix, and the bounce at every phase is its one product with the
cells' albedo times direct light. Work over pixels, samples, pairs or cells is split in batches of at
most ``BATCH_BYTES`` (or a quarter of a GPU's free memory).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from pstoolkit._shared import devices
from pstoolkit_dualres.bounce import MIN_NZ, RADIUS_CELLS, Cells

if TYPE_CHECKING:
    from pstoolkit_dualres.problem import EventTerms, FrameTerms

# Device memory a batch of phases, samples or pairs may take, at most (``devices.memory_budget``).
BATCH_BYTES = 1 << 30


def _rows_per_batch(device: torch.device, row_bytes: int) -> int:
    return max(1, devices.memory_budget(device, BATCH_BYTES) // max(row_bytes, 1))


def cell_direct_there(cells: Cells, normal: Tensor, lit: Tensor, directions: np.ndarray) -> Tensor:
    """``cells.direct`` of the (P, 3) float64 ``normal`` and (T, P) bool ``lit`` on their device, for the
    (T, 3) unit ``directions``: (Hc, Wc, T) float64 there."""
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
    return out.reshape(*cells.shape, len(light))


def bounce_there(cells: Cells, normal: np.ndarray, albedo: np.ndarray, height: np.ndarray, direct: Tensor,
                 period_us: float) -> DeviceBounce:
    """``cells.bounce`` on the device of ``direct`` (Hc, Wc, T) float64 (``cell_direct_there``), of the
    frame pixels' ``normal``, ``albedo`` (H, W, 3) and ``height`` (H, W) pooled on the host."""
    device = direct.device
    surface = cells.surface(normal, albedo, height)
    point, cell_normal, albedo_there, inside, cell_height = (
        torch.as_tensor(np.asarray(a), device=device) for a in
        (surface.point, surface.normal, surface.albedo, surface.inside, surface.height))
    out = _sum_there(point, cell_normal, albedo_there, direct, inside, cell_height, RADIUS_CELLS)
    return DeviceBounce(out.permute(1, 0, 2).to(torch.float32).contiguous(),
                        torch.as_tensor(cells.cell, dtype=torch.int64, device=device), float(period_us))


def _sum_there(point: Tensor, normal: Tensor, albedo: Tensor, direct: Tensor, inside: Tensor, height: Tensor,
               radius: int) -> Tensor:
    """``bounce._bounce`` of (Hc, Wc, ...) tensors on one device (``point``, ``normal``, ``albedo`` (…, 3),
    ``direct`` (…, T) and ``height`` float64, ``inside`` bool): (C, T, 3) float64 there, C = Hc·Wc
    (module docstring)."""
    hc, wc = inside.shape
    n_cells, t_count = hc * wc, direct.shape[-1]
    device = point.device
    point, normal, height, inside = point.reshape(-1, 3), normal.reshape(-1, 3), height.reshape(-1), inside.reshape(-1)
    dv, du = (a.reshape(-1) for a in torch.meshgrid(torch.arange(-radius, radius + 1, device=device),
                                                     torch.arange(-radius, radius + 1, device=device), indexing="ij"))
    near = ((du != 0) | (dv != 0)) & (du * du + dv * dv <= radius * radius)
    dv, du = dv[near], du[near]
    cell = torch.arange(n_cells, device=device)
    v, u = cell // wc, cell % wc
    # the march's steps s = 1 … steps − 1 along the segment, steps = max(|du|, |dv|) ≤ radius
    s = torch.arange(1, max(radius, 2), device=device, dtype=torch.float64)
    budget = devices.memory_budget(device, BATCH_BYTES)
    weight = torch.zeros((n_cells, n_cells), dtype=torch.float64, device=device)
    # bytes of a (offset, cell) pair: its march's float64 rows and their tests
    step = max(1, budget // (8 * 8 * s.numel() * n_cells))
    for first in range(0, du.numel(), step):
        bdv, bdu = dv[first : first + step, None], du[first : first + step, None]
        vy, uy = v[None] + bdv, u[None] + bdu
        there = (vy >= 0) & (vy < hc) & (uy >= 0) & (uy < wc) & inside[None]
        neighbour = vy.clamp(0, hc - 1) * wc + uy.clamp(0, wc - 1)
        there &= inside[neighbour]
        k, c = torch.nonzero(there, as_tuple=True)
        n = neighbour[k, c]
        d = point[n] - point[c]
        dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
        r2 = dx * dx + dy * dy + dz * dz
        r = torch.sqrt(r2)
        nc, nn = normal[c], normal[n]
        cos_x = (nc[:, 0] * dx + nc[:, 1] * dy + nc[:, 2] * dz) / r
        cos_y = -(nn[:, 0] * dx + nn[:, 1] * dy + nn[:, 2] * dz) / r
        facing = torch.nonzero((cos_x > 0.0) & (cos_y > 0.0), as_tuple=True)[0]
        k, c, n, dz, r2, cos_x, cos_y = (a[facing] for a in (k, c, n, dz, r2, cos_x, cos_y))
        pdu, pdv = bdu[k, 0], bdv[k, 0]
        steps = torch.maximum(pdu.abs(), pdv.abs()).to(torch.float64)
        f = s[None] / steps[:, None]
        su = torch.round(u[c, None].to(torch.float64) + f * pdu[:, None].to(torch.float64)).to(torch.int64)
        sv = torch.round(v[c, None].to(torch.float64) + f * pdv[:, None].to(torch.float64)).to(torch.int64)
        sample = sv.clamp(0, hc - 1) * wc + su.clamp(0, wc - 1)
        pz = point[c, 2, None]
        blocked = ((s[None] < steps[:, None]) & inside[sample] & (height[sample] > pz + f * dz[:, None] + 0.5)).any(dim=1)
        seen = ~blocked
        c, n = c[seen], n[seen]
        weight[c, n] = cos_x[seen] * cos_y[seen] / (math.pi * r2[seen]) / torch.clamp(normal[n, 2], min=MIN_NZ)
    reflected = (albedo.reshape(-1, 1, 3) * direct.reshape(-1, t_count, 1)).reshape(n_cells, t_count * 3)
    return (weight @ reflected).reshape(n_cells, t_count, 3)


@dataclass
class DeviceBounce:
    """``bounce.Bounce`` on a torch device: ``value`` (T, C, 3) float32 and ``cell`` (P,) int64 there."""

    value: Tensor
    cell: Tensor
    period_us: float

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
