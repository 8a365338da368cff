"""``base.ShadowMask``'s lookups on a torch device, for the solvers that run there: a mask applied to a
fit's samples and event pairs asks "in shadow at t?" and "how long in shadow between t0 and t1?" of
tens of millions of (pixel, time) queries at a large capture, whose answers stay on the device.

Each lookup is the host's float64 expression of the same inputs (``intervals.ShadowTable``): the
searches of ``contains`` and ``shadowed_us``, and the per-row sum of ``overlap_on_grid`` for
``shadowed_grid``, so the answers equal the host's (a test holds them to it). The host searches only
the queries of pixels with any interval (a cache miss per step of a search in a table of millions of
keys); a device searches them all, which gives the same answers: a pixel without an interval finds an
earlier pixel's row, whose keys end before its own begin. Queries are taken in batches of at most
``BATCH_BYTES`` (or a quarter of a GPU's free memory).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from pstoolkit._shared import devices
from pstoolkit.shadows.base import ShadowMask

# Device memory a batch of queries may take for its float64 keys and slots, at most (``devices.memory_budget``).
BATCH_BYTES = 1 << 28
# Bytes a query takes in a batch: its keys, slots and partial sums (float64 and int64).
_QUERY_BYTES = 96


class DeviceShadowMask:
    """``ShadowMask`` ``mask`` on ``device``: its merged intervals and cells moved once, every lookup
    answered there. Frame pixels are (N,) int64 tensors, times float64 µs tensors on the device."""

    def __init__(self, mask: ShadowMask, device: str | torch.device) -> None:
        self.device = torch.device(device)
        table = mask.table
        self.period_us = float(table.period_us)
        self.t0_us = float(mask.t0_us)
        self.start, self.end, self.before = (torch.as_tensor(a, dtype=torch.float64, device=self.device)
                                             for a in (table.start, table.end, table.before))
        self.cell = torch.as_tensor(mask.cell, dtype=torch.int64, device=self.device)
        self._batch = max(1, devices.memory_budget(self.device, BATCH_BYTES) // _QUERY_BYTES)

    def __len__(self) -> int:
        """Merged intervals (0: no pixel is ever in shadow)."""
        return int(self.start.numel())

    def _base(self, cell: Tensor) -> Tensor:
        """The key of phase 0 of each cell: cell·2·period, as the host's table keys it."""
        return cell.to(torch.float64) * (2.0 * self.period_us)

    def _key(self, cell: Tensor, phase_us: Tensor) -> Tensor:
        return self._base(cell) + phase_us

    def _phase(self, t_us: Tensor) -> Tensor:
        """``t_us`` modulo the period as ``numpy.mod`` takes it: fmod (exact), then + period where negative;
        the same bits on every device, where a remainder by a - b·floor(a / b) may round."""
        mod = torch.fmod(t_us, self.period_us)
        return torch.where(mod < 0, mod + self.period_us, mod)

    def _batched(self, compute: Callable[..., Tensor], *arrays: Tensor) -> Tensor:
        """``compute`` of the flattened (broadcast) ``arrays`` a batch at a time, in their shape."""
        arrays = torch.broadcast_tensors(*arrays)
        flat = [a.reshape(-1) for a in arrays]
        size = flat[0].numel()
        if size <= self._batch:
            return compute(*flat).reshape(arrays[0].shape)
        return torch.cat([compute(*(a[i : i + self._batch] for a in flat)) for i in range(0, size, self._batch)]).reshape(arrays[0].shape)

    def contains(self, frame_pixel: Tensor, t_us: Tensor) -> Tensor:
        """``ShadowMask.contains``: bool, frame pixel ``frame_pixel`` in shadow at time ``t_us`` (same shape)."""
        if len(self) == 0:
            return torch.zeros(torch.broadcast_shapes(frame_pixel.shape, t_us.shape), dtype=torch.bool, device=self.device)
        return self._batched(self._contains, frame_pixel, t_us)

    def _contains(self, frame_pixel: Tensor, t_us: Tensor) -> Tensor:
        key = self._key(self.cell[frame_pixel], self._phase(t_us - self.t0_us))
        slot = torch.searchsorted(self.start, key, right=True) - 1
        safe = slot.clamp(min=0)
        return (slot >= 0) & (key <= self.end[safe]) & (key >= self.start[safe])

    def contains_grid(self, frame_pixel: Tensor, t_us: Tensor) -> Tensor:
        """``ShadowMask.contains_grid``: (T, N) bool for every frame pixel (N,) at every time ``t_us`` (T,)."""
        return self.contains(frame_pixel[None, :], t_us[:, None])

    def _cumulative(self, key: Tensor) -> Tensor:
        """``ShadowTable._cumulative``: total shadow time of all intervals up to ``key``."""
        slot = torch.searchsorted(self.start, key, right=True) - 1
        safe = slot.clamp(min=0)
        first = self.start[safe]
        partial = torch.clamp(key - first, torch.zeros_like(key), self.end[safe] - first)
        return torch.where(slot >= 0, self.before[safe] + partial, torch.zeros_like(key))

    def shadowed_us(self, frame_pixel: Tensor, t0_us: Tensor, t1_us: Tensor) -> Tensor:
        """``ShadowMask.shadowed_us``: float64 µs frame pixel ``frame_pixel`` spends in shadow between times
        ``t0_us`` ≤ ``t1_us`` (same shapes, at most one period apart)."""
        if len(self) == 0:
            shape = torch.broadcast_shapes(frame_pixel.shape, t0_us.shape, t1_us.shape)
            return torch.zeros(shape, dtype=torch.float64, device=self.device)
        return self._batched(self._shadowed_us, frame_pixel, t0_us, t1_us)

    def _shadowed_us(self, frame_pixel: Tensor, t0_us: Tensor, t1_us: Tensor) -> Tensor:
        cell = self.cell[frame_pixel]
        t0 = t0_us - self.t0_us
        period = self.period_us
        # the host's span: t1 relative to the phase origin as t0 + (t1 − t0)
        span = torch.clamp((t0 + (t1_us - t0_us)) - t0, 0.0, period)
        a = self._phase(t0)
        b = a + span
        wraps = b > period
        low = self._cumulative(self._key(cell, a))
        high = self._cumulative(self._key(cell, torch.clamp(b, max=period)))
        wrapped = (self._cumulative(self._key(cell, torch.where(wraps, b - period, torch.zeros_like(b))))
                   - self._cumulative(self._key(cell, torch.zeros_like(a))))
        return high - low + torch.where(wraps, wrapped, torch.zeros_like(wrapped))

    def shadowed_grid(self, frame_pixel: Tensor, t0_us: Tensor, t1_us: Tensor) -> Tensor:
        """``ShadowMask.shadowed_grid``: (T, N) float64 µs for every frame pixel (N,) in every window
        ``t0_us`` ≤ ``t1_us`` (T,), each at most one period long; summed row by row of each pixel's
        intervals as ``interval_kernels.overlap_on_grid`` sums them."""
        period = self.period_us
        t0 = t0_us - self.t0_us
        a = self._phase(t0)
        b = a + torch.clamp((t1_us - self.t0_us) - t0, 0.0, period)
        out = torch.zeros((a.numel(), frame_pixel.numel()), dtype=torch.float64, device=self.device)
        if len(self) == 0 or frame_pixel.numel() == 0:
            return out
        step = max(1, self._batch // max(a.numel(), 1))
        for first in range(0, frame_pixel.numel(), step):
            part = slice(first, first + step)
            out[:, part] = self._overlap(self._base(self.cell[frame_pixel[part]]), a, b)
        return out

    def _overlap(self, base: Tensor, a: Tensor, b: Tensor) -> Tensor:
        """(T, n): the length of [a, b] (T,) (wrapping past the period to 0) inside each pixel's intervals,
        keys offset by ``base`` (n,)."""
        period = self.period_us
        lo = torch.searchsorted(self.start, base)
        count = torch.searchsorted(self.start, base + period, right=True) - lo
        x0, x1 = base[None, :] + a[:, None], base[None, :] + torch.clamp(b, max=period)[:, None]
        w0, w1 = base[None, :], base[None, :] + torch.clamp(b - period, min=0.0)[:, None]
        wraps = (b > period)[:, None]
        zero = torch.zeros((), dtype=torch.float64, device=self.device)
        total = torch.zeros_like(x0)
        last = len(self) - 1
        for r in range(int(count.max()) if count.numel() else 0):
            row = (lo + r).clamp(max=last)
            taken = (r < count)[None, :]
            first, end = self.start[row][None, :], self.end[row][None, :]
            total = total + torch.where(taken, torch.clamp(torch.minimum(x1, end) - torch.maximum(x0, first), min=0.0), zero)
            total = total + torch.where(taken & wraps, torch.clamp(torch.minimum(w1, end) - torch.maximum(w0, first), min=0.0), zero)
        return total
