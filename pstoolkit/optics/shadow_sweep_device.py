"""``shadow_sweep.ShadowCaster.margins`` on a torch device, for the solvers that run there.

The compiled sweep walks each light's parallel lines column by column, keeping their running maximum
of occluder − ramp; a GPU takes the same quantities all at once instead: for a batch of lights, the
occluder samples of every line at every column (interpolated between the two rows the line passes,
as the sweep does), their maximum over the columns after each one by one running maximum from the far
end (``torch.cummax``), and the margin
of each pixel from the two lines around it. Every value is the sweep's own float32 expression of the
same inputs and a maximum is exact, so the margins equal the compiled sweep's (a test holds them to
it). Memory: a few (lines × columns) float32 arrays per light of a batch, bounded by
``BATCH_BYTES`` or a quarter of a GPU's free memory.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from pstoolkit._shared import devices
from pstoolkit.optics.shadow_sweep import _LOW_MARGIN, _NO_OCCLUDER, sweep_groups

# Device memory a batch of lights may take for its (lines × columns) arrays, at most (``devices.memory_budget``).
BATCH_BYTES = 1 << 30


class DeviceCaster:
    """``ShadowCaster`` of one height map on ``device``: the maps in the four sweep orientations, made
    the first time a light needs each."""

    def __init__(self, depth: np.ndarray, mask: np.ndarray, device: str | torch.device) -> None:
        depth = np.asarray(depth, dtype=np.float64)
        mask = np.asarray(mask, dtype=bool)
        self.device = torch.device(device)
        self.shape = mask.shape
        self.occluder = torch.as_tensor(np.where(mask, depth, _NO_OCCLUDER).astype(np.float32), device=self.device)
        self.height = torch.as_tensor(depth.astype(np.float32), device=self.device)
        self.mask = torch.as_tensor(mask, device=self.device)
        self._oriented: dict[tuple[bool, bool], tuple[Tensor, Tensor, Tensor]] = {}

    def _maps(self, transpose: bool, flip: bool) -> tuple[Tensor, Tensor, Tensor]:
        """The occluder, height and mask oriented so the light comes from increasing columns, each
        stored (columns, rows) as the compiled sweep reads them."""
        if (transpose, flip) not in self._oriented:
            oriented = [a.T if transpose else a for a in (self.occluder, self.height, self.mask)]
            if flip:
                oriented = [a.flip(1) for a in oriented]
            self._oriented[transpose, flip] = tuple(a.T.contiguous() for a in oriented)  # type: ignore[assignment]
        return self._oriented[transpose, flip]

    def margins(self, directions: np.ndarray) -> Tensor:
        """(T, H, W) float32 ``shadow_margin`` for ``directions`` (T, 3) unit, on the device."""
        l = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
        h, w = self.shape
        out = torch.full((l.shape[0], h, w), _LOW_MARGIN, dtype=torch.float32, device=self.device)
        budget = devices.memory_budget(self.device, BATCH_BYTES)
        for transpose, flip, index, k, rise in sweep_groups(l):
            occluder, height, inside = self._maps(transpose, flip)
            cols, rows = occluder.shape
            lines = rows + int(np.ceil(np.max(np.abs(k)) * (cols - 1))) + 2
            batch = max(1, budget // (4 * 4 * cols * (lines + rows + 2)))
            for first in range(0, index.size, batch):
                part = slice(first, first + batch)
                oriented = _oriented_margins(occluder, height, inside, k[part], rise[part], lines)  # (G, C, R)
                margin = oriented.transpose(1, 2)  # (G, R, C) of the oriented maps
                if flip:
                    margin = margin.flip(2)
                out[torch.as_tensor(index[part], device=self.device)] = margin.transpose(1, 2) if transpose else margin
        return out


def _oriented_margins(occluder: Tensor, height: Tensor, inside: Tensor, k: np.ndarray, rise: np.ndarray, lines: int) -> Tensor:
    """(G, C, R) margins of lights g with the oriented maps (C, R) (``shadow_sweep._sweep``'s quantities:
    line j crosses column c at row base + j, base = first_base + k·c, climbing rise·c)."""
    device = occluder.device
    cols, rows = occluder.shape
    c = np.arange(cols, dtype=np.float64)
    first_base = np.floor(np.minimum(0.0, -k * (cols - 1))) - 1.0
    base = first_base[:, None] + k[:, None] * c[None, :]  # (G, C) float64, as the sweep computes it
    ramp = torch.as_tensor((rise[:, None] * c[None, :]).astype(np.float32), device=device)[..., None]
    i0 = np.floor(base)
    f = torch.as_tensor((base - i0).astype(np.float32), device=device)[..., None]
    q0 = np.floor(-base)
    w = torch.as_tensor((-base - q0).astype(np.float32), device=device)[..., None]
    one = torch.tensor(1.0, dtype=torch.float32, device=device)
    # every line's occluder sample at every column: rows i0 + j and i0 + j + 1, outside the map the sentinel
    pad = lines + 2
    padded = torch.full((cols, rows + 2 * pad), _NO_OCCLUDER, dtype=torch.float32, device=device)
    padded[:, pad : pad + rows] = occluder
    column = torch.arange(cols, device=device)[None, :]
    start = torch.as_tensor(i0.astype(np.int64) + pad, device=device)
    pairs = padded.unfold(1, lines + 1, 1)[column, start]  # (G, C, lines + 1)
    # (1 − f)·a + f·b, as the sweep: not a + f·(b − a)
    sample = pairs[..., :-1] * (one - f) + pairs[..., 1:] * f - ramp
    del pairs
    # the running maximum a column's pixels see: over the columns after it (towards the light), one scan
    # from the far end (a log-step scan takes log2(columns) passes over the lines, each reading them thrice)
    backwards = torch.full_like(sample, _NO_OCCLUDER)
    backwards[:, 1:] = sample[:, 1:].flip(1)
    del sample
    after = torch.cummax(backwards, dim=1).values.flip(1)
    del backwards
    # pixel row r lies between lines q0 + r and q0 + r + 1
    around = after.unfold(2, rows + 1, 1)[torch.arange(len(k), device=device)[:, None], column,
                                          torch.as_tensor(q0.astype(np.int64), device=device)]  # (G, C, R + 1)
    del after
    own = height[None] - ramp
    low = torch.tensor(_LOW_MARGIN, dtype=torch.float32, device=device)
    margin = (torch.maximum(around[..., :-1] - own, low) * (one - w) + torch.maximum(around[..., 1:] - own, low) * w)
    return torch.where(inside[None], margin, low)
