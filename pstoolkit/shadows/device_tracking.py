"""The swept shadows' bookkeeping on a torch device: ``intervals.RunCollector`` and
``edge_tracking.EdgeTracker`` fed the blocks ``surface_sweep.surface_shadow_blocks`` sweeps on a device,
so that only the runs and edges found come back to the host, not the (steps, P) shadows (0.75 GB at
1024² and 720 steps). Each gives what its host counterpart gives, in the same order (tests hold them
to it); ``run_collector`` and ``edge_tracker`` pick the host's or the device's for a device.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from pstoolkit._shared import devices
from pstoolkit.shadows.edge_tracking import EdgeTracker, SuperPixels
from pstoolkit.shadows.intervals import RunCollector, ShadowIntervals


class DeviceRunCollector:
    """``RunCollector`` of (n, P) bool blocks on a torch device: the rows where each column's value
    changes are kept there, and paired into runs when ``intervals`` is asked."""

    def __init__(self, columns: int, device: str | torch.device) -> None:
        self.previous = torch.zeros(columns, dtype=torch.bool, device=device)
        self.rows = 0
        self._opens: list[tuple[Tensor, Tensor]] = []
        self._closes: list[tuple[Tensor, Tensor]] = []

    def feed(self, block: Tensor) -> None:
        """The next (n, P) rows, bool, on the collector's device."""
        if block.shape[0] == 0:
            return
        rows = torch.cat([self.previous[None], block])
        change = rows[1:] != rows[:-1]
        k, c = torch.nonzero(change, as_tuple=True)
        opening = block[k, c]
        self._opens.append((k[opening] + self.rows, c[opening]))
        self._closes.append((k[~opening] + self.rows, c[~opening]))
        self.previous = block[-1].clone()
        self.rows += block.shape[0]

    def _changes(self) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """(row, column) of every run's opening and of its closing (runs still open close at the rows fed)."""
        device = self.previous.device
        still = torch.nonzero(self.previous, as_tuple=True)[0]
        empty = torch.empty(0, dtype=torch.int64, device=device)
        opens = [(empty, empty), *self._opens]
        closes = [(empty, empty), *self._closes, (torch.full_like(still, self.rows), still)]
        open_row, open_column = (torch.cat([part[i] for part in opens]) for i in range(2))
        close_row, close_column = (torch.cat([part[i] for part in closes]) for i in range(2))
        return open_row, open_column, close_row, close_column

    def grid_at(self, columns: Tensor) -> Tensor:
        """(rows fed, C) bool: the rows fed so far at ``columns`` (C,) int64 on the device, distinct,
        rebuilt from the runs: the +1 of each opening and −1 of each closing written into a table (no two
        changes of a column share a row), its running sum over the rows."""
        open_row, open_column, close_row, close_column = self._changes()
        count = columns.numel()
        # the changes of other columns go to a last column, dropped: no boolean index, no read back
        position = torch.full((self.previous.numel(),), count, dtype=torch.int64, device=columns.device)
        position[columns] = torch.arange(count, device=columns.device)
        table = torch.zeros((self.rows + 1, count + 1), dtype=torch.int8, device=columns.device)
        for row, column, sign in ((open_row, open_column, 1), (close_row, close_column, -1)):
            table[row, position[column]] = sign
        return torch.cumsum(table[:-1, :count], dim=0, dtype=torch.int8) > 0

    def intervals(self, period_us: float, pixels: np.ndarray | None = None) -> ShadowIntervals:
        """``RunCollector.intervals``: every run of the rows fed so far, column by column in time order."""
        open_row, open_column, close_row, close_column = self._changes()
        # a column's changes alternate from an opening: its k-th opening and k-th closing make its k-th run
        stride = self.rows + 1
        order = torch.argsort(open_column * stride + open_row)
        column, first = open_column[order], open_row[order]
        after = close_row[torch.argsort(close_column * stride + close_row)]
        names = np.arange(self.previous.numel()) if pixels is None else np.asarray(pixels, dtype=np.int64)
        step_us = float(period_us) / max(self.rows, 1)
        first_np, after_np = first.cpu().numpy(), after.cpu().numpy()
        return ShadowIntervals(names[column.cpu().numpy()], first_np * step_us, after_np * step_us)


class DeviceEdgeTracker:
    """``EdgeTracker`` of (n, P) bool blocks on a torch device: each super pixel's shadowed count per
    direction, its state and its changes there; ``edges`` and ``pixel_bins`` come back as the host's."""

    def __init__(self, groups: SuperPixels, device: str | torch.device, *, count_pixels: bool = False) -> None:
        self.groups = groups
        key = str(torch.device(device))
        if key not in groups.there:
            # moved once for every tracker of the same super pixels (a calibration sweeps 13 times)
            groups.there[key] = tuple(torch.as_tensor(a, device=device) for a in
                                      (groups.group.astype(np.int64), groups.used.astype(np.int64), groups.needed))
        self.group, self.used, self.needed = groups.there[key]
        self._pixel_bins = torch.zeros(groups.group.size, dtype=torch.int64, device=device) if count_pixels else None
        self._bins: list[Tensor] = []
        self._pixel: list[Tensor] = []
        self._entering: list[Tensor] = []
        self._first: Tensor | None = None
        self._last: Tensor | None = None
        self.steps = 0

    @property
    def pixel_bins(self) -> np.ndarray | None:
        """(P,) int32 the time bins each masked frame pixel is shadowed, or None without ``count_pixels``."""
        return None if self._pixel_bins is None else self._pixel_bins.cpu().numpy().astype(np.int32)

    def feed(self, block: Tensor) -> None:
        """The next (n, P) bool rows of the surface's shadows, on the tracker's device."""
        if self._pixel_bins is not None:
            self._pixel_bins += block.sum(dim=0)
        # counts of a few pixels each: exact in float32, whatever order the device adds them in
        counts = torch.zeros((block.shape[0], self.needed.numel()), dtype=torch.float32, device=block.device)
        counts.index_add_(1, self.group, block.to(torch.float32))
        state = counts >= self.needed
        if self._first is None:
            self._first = state[0]
        before = torch.cat([state[:1] if self._last is None else self._last[None], state[:-1]])
        k, e = torch.nonzero(state != before, as_tuple=True)
        self._bins.append(k + self.steps)
        self._pixel.append(e)
        self._entering.append(state[k, e])
        self._last = state[-1]
        self.steps += block.shape[0]

    def edges_there(self) -> tuple[Tensor, Tensor, Tensor]:
        """``EdgeTracker.edges`` on the device: (time bin, super pixel, entering) of every edge, in time
        order, int64, int64 and bool."""
        if self._first is None or self._last is None:
            empty = torch.empty(0, dtype=torch.int64, device=self.used.device)
            return empty, empty, torch.empty(0, dtype=torch.bool, device=self.used.device)
        wrap = torch.nonzero(self._first != self._last, as_tuple=True)[0]
        bins = torch.cat([torch.zeros_like(wrap), *self._bins])
        position = torch.cat([wrap, *self._pixel])
        entering = torch.cat([self._first[wrap], *self._entering])
        return bins, self.used[position], entering

    def edges(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``EdgeTracker.edges``: (time bin, super pixel, entering) of every edge, in time order."""
        bins, pixel, entering = self.edges_there()
        return bins.cpu().numpy(), pixel.cpu().numpy(), entering.cpu().numpy()


def run_collector(columns: int, device: str) -> RunCollector | DeviceRunCollector:
    """The ``RunCollector`` of ``columns`` for the blocks ``surface_sweep.surface_shadow_blocks`` gives
    on the torch ``device``: the host's on the CPU, else its device copy."""
    return RunCollector(columns) if devices.on_host(device) else DeviceRunCollector(columns, device)


def edge_tracker(groups: SuperPixels, device: str, *, count_pixels: bool = False) -> EdgeTracker | DeviceEdgeTracker:
    """The ``EdgeTracker`` of ``groups`` for the blocks ``surface_shadow_blocks`` gives on the torch
    ``device``: the host's on the CPU, else its device copy."""
    if devices.on_host(device):
        return EdgeTracker(groups, count_pixels=count_pixels)
    return DeviceEdgeTracker(groups, device, count_pixels=count_pixels)
