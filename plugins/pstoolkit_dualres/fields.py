"""The surface representations of DualResPS (eq. 19): per masked frame pixel a unit normal, the raw
channels of the per-pixel maps of the BRDF (the diffuse albedo) and those of its smooth materials
(``reflectance.FitModel``).

``PyramidField`` (the ``fast`` preset) holds the normal and the per-pixel maps as a Laplacian pyramid
over the frame grid: a pixel's value is the sum of its own level and of every coarser level
interpolated bilinearly to it. A coarse cell gathers the gradients of all the pixels under it, so
the smooth part of the surface converges in few steps where the data of single pixels is weak
(saturated highlights, grazing rims, the dark side of a shadow), while the finest level keeps every
pixel's own detail where the frames resolve it; a penalty on the finer levels (``smoothness``)
prefers the coarse explanation unless the data asks for detail. The smooth materials live on a
pyramid over the event grid (their resolution, main §1), interpolated to the frame pixels through
the calibrated affine. Nothing but interpolation is evaluated, so a step costs the rendering alone.

``NeuralField`` (the ``paper`` preset) is the paper's network (supplement §2.4): positional encoding
of the pixel coordinate (10 frequencies), an 8-layer ReLU MLP of width 256 with the input
concatenated again at layer 4, a normal head on the backbone, and a material head (one projection
layer and 4 layers of width 128) giving the per-pixel and smooth channels.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from pstoolkit_dualres.closed_form import fill
from pstoolkit_dualres.gather import gather_sum

FieldOutput = tuple[Tensor, Tensor, Tensor]
"""(normal (P, 3) unit, per-pixel raw channels (P, Cp), smooth raw channels (P, Cs))."""
# The coarsest level of a pyramid has at least this many cells along its shorter side.
COARSEST_CELLS = 8


def _unit(v: Tensor) -> Tensor:
    return v / torch.sqrt(torch.sum(v * v, dim=-1, keepdim=True) + 1e-12)


def pyramid_levels(height: int, width: int, cap: int) -> int:
    """Levels of halving from height×width until the shorter side would fall below COARSEST_CELLS,
    at most ``cap``."""
    side = min(height, width)
    levels = 1
    while levels < cap and side / 2 ** levels >= COARSEST_CELLS:
        levels += 1
    return levels


def decompose(image: Tensor, levels: int) -> list[Tensor]:
    """Laplacian pyramid of ``image`` (1, C, H, W): the finest level first; ``collapse`` sums it back."""
    gauss = [image]
    for _ in range(1, levels):
        gauss.append(F.avg_pool2d(gauss[-1], 2, ceil_mode=True))
    out = [gauss[-1]]
    for finer in reversed(gauss[:-1]):
        out.append(finer - F.interpolate(out_sum(out), size=finer.shape[-2:], mode="bilinear", align_corners=False))
    return out[::-1]


def out_sum(coarse_first: list[Tensor]) -> Tensor:
    """The image of a pyramid given coarsest first (the levels collected so far)."""
    image = coarse_first[0]
    for level in coarse_first[1:]:
        image = F.interpolate(image, size=level.shape[-2:], mode="bilinear", align_corners=False) + level
    return image


def collapse(levels: list[Tensor] | nn.ParameterList) -> Tensor:
    """The image (1, C, H, W) of a Laplacian pyramid (finest level first)."""
    return out_sum(list(levels)[::-1])


class PyramidField(nn.Module):
    """Normal and per-pixel maps on a Laplacian pyramid over the H×W frame grid, started from the
    closed form (``init_normal`` (P, 3), ``init_pixel_raw`` (P, Cp) at the masked pixels ``pixels``);
    smooth materials on a pyramid over the He×We event grid, started at ``smooth_init`` (Cs,),
    read at the frame pixels through bilinear ``taps`` ((P, 4) event-grid indices, (P, 4) weights).
    ``smoothness`` weighs the penalty on the finer levels of the normal (``penalty``)."""

    def __init__(
        self,
        shape: tuple[int, int],
        pixels: np.ndarray,
        init_normal: Tensor,
        init_pixel_raw: Tensor,
        event_shape: tuple[int, int],
        taps: tuple[Tensor, Tensor],
        smooth_init: Tensor,
        *,
        levels: int = 6,
        smooth_levels: int = 3,
        smoothness: float = 0.0,
    ) -> None:
        super().__init__()
        h, w = shape
        device, dtype = init_normal.device, init_normal.dtype
        self.shape = shape
        self.register_buffer("pixels", torch.as_tensor(pixels, dtype=torch.int64, device=device))
        values = torch.cat([init_normal, init_pixel_raw], dim=1)
        self.channels = values.shape[1]
        full = np.zeros((h * w, self.channels), dtype=np.float32)
        full[pixels] = values.detach().cpu().numpy()
        known = np.zeros(h * w, dtype=bool)
        known[pixels] = True
        # the pixels outside the mask continue the surface, so coarse cells on the rim average sense
        full = fill(full.reshape(h, w, -1), known.reshape(h, w), np.ones((h, w), dtype=bool))
        image = torch.as_tensor(full, dtype=dtype, device=device).permute(2, 0, 1)[None]
        self.levels = nn.ParameterList(nn.Parameter(level) for level in decompose(image, pyramid_levels(h, w, levels)))
        he, we = event_shape
        self.smooth_channels = smooth_init.shape[0]
        grid = smooth_init.to(device, dtype)[None, :, None, None].expand(1, -1, he, we)
        self.smooth = nn.ParameterList(
            nn.Parameter(level.contiguous()) for level in decompose(grid, pyramid_levels(he, we, smooth_levels))
        ) if self.smooth_channels else nn.ParameterList()
        self.register_buffer("tap_index", taps[0])
        self.register_buffer("tap_weight", taps[1].to(dtype))
        self.smoothness = smoothness

    def surface_parameters(self) -> list[nn.Parameter]:
        return list(self.levels)

    def material_parameters(self) -> list[nn.Parameter]:
        return list(self.smooth)

    def _values(self) -> Tensor:
        # index_select differentiates into index_add_, advanced indexing into a slower index_put_
        return collapse(self.levels)[0].reshape(self.channels, -1).index_select(1, self.pixels).T

    def forward(self, index: Tensor | None = None) -> FieldOutput:
        """The maps at the masked pixels ``index`` (all when None)."""
        values = self._values()
        if index is not None:
            values = values[index]
        if self.smooth_channels:
            grid = collapse(self.smooth)[0].reshape(self.smooth_channels, -1).T
            taps, weights = (self.tap_index, self.tap_weight) if index is None else (self.tap_index[index], self.tap_weight[index])
            smooth = gather_sum(grid, taps, weights)
        else:
            smooth = values.new_zeros((values.shape[0], 0))
        return _unit(values[:, :3]), values[:, 3:], smooth

    def penalty(self) -> Tensor:
        """``smoothness`` × Σ over the levels finer than the coarsest of the mean squared normal
        channels, each level weighted 4× its next coarser one (a finer level's detail costs more)."""
        levels = list(self.levels)
        total = levels[0].new_zeros(())
        for depth, level in enumerate(levels[:-1]):
            total = total + 4.0 ** (-depth) * level[:, :3].pow(2).mean()
        return self.smoothness * total

    @torch.no_grad()
    def reset(self, index: Tensor, normal: Tensor, pixel_raw: Tensor) -> None:
        """Set the masked pixels ``index`` to ``normal`` (N, 3) and ``pixel_raw`` (N, Cp), through
        the finest level (coarser levels, shared with neighbours, are kept)."""
        h, w = self.shape
        target = torch.cat([normal, pixel_raw], dim=1).to(self.levels[0].dtype)
        current = self._values()[index]
        flat = self.levels[0].view(self.channels, h * w)
        flat[:, self.pixels[index]] += (target - current).T


def positional_encoding(coords: Tensor, frequencies: int) -> Tensor:
    """(P, 2) coordinates in [−1, 1] → (P, 2 + 4·frequencies): the coordinate, then sin and cos of
    2^k·π·coordinate for k < frequencies."""
    scales = (2.0 ** torch.arange(frequencies, dtype=coords.dtype, device=coords.device)) * math.pi
    angles = (coords[:, :, None] * scales).reshape(coords.shape[0], -1)
    return torch.cat([coords, torch.sin(angles), torch.cos(angles)], dim=-1)


class NeuralField(nn.Module):
    """The paper's coordinate MLP: M(x; Θ) → n, per-pixel and smooth raw channels, started facing the
    camera with the raw start values ``pixel_init`` (Cp,) and ``smooth_init`` (Cs,)."""

    def __init__(
        self,
        coords: Tensor,
        pixel_init: Tensor,
        smooth_init: Tensor,
        *,
        frequencies: int = 10,
        width: int = 256,
        depth: int = 8,
        skip: int = 4,
        material_width: int = 128,
        material_depth: int = 4,
    ) -> None:
        super().__init__()
        self.register_buffer("encoded", positional_encoding(coords, frequencies))
        d_in = self.encoded.shape[1]
        self.skip = skip
        self.split = pixel_init.shape[0]
        self.layers = nn.ModuleList(
            nn.Linear(d_in if i == 0 else width + (d_in if i == skip else 0), width) for i in range(depth)
        )
        self.normal_head = nn.Linear(width, 3)
        material: list[nn.Module] = [nn.Linear(width, width)]
        for i in range(material_depth):
            material += [nn.Linear(width if i == 0 else material_width, material_width), nn.ReLU()]
        self.material = nn.Sequential(*material)
        self.material_out = nn.Linear(material_width, pixel_init.shape[0] + smooth_init.shape[0])
        with torch.no_grad():
            self.normal_head.weight.mul_(0.1)
            self.normal_head.bias.copy_(torch.tensor([0.0, 0.0, 1.0]))
            self.material_out.weight.mul_(0.1)
            self.material_out.bias.copy_(torch.cat([pixel_init, smooth_init]))

    def surface_parameters(self) -> list[nn.Parameter]:
        return list(self.parameters())

    def material_parameters(self) -> list[nn.Parameter]:
        return []

    def forward(self, index: Tensor | None = None) -> FieldOutput:
        """The maps at the masked pixels ``index`` (all when None)."""
        x = self.encoded if index is None else self.encoded[index]
        h = x
        for i, layer in enumerate(self.layers):
            if i == self.skip:
                h = torch.cat([h, x], dim=-1)
            h = torch.relu(layer(h))
        out = self.material_out(self.material(h))
        return _unit(self.normal_head(h)), out[:, : self.split], out[:, self.split :]

    def penalty(self) -> Tensor:
        """No explicit smoothness: the network's spectral bias is the paper's prior."""
        return self.encoded.new_zeros(())
