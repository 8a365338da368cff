"""The surface representations of DualResPS (eq. 19): per masked frame pixel, a unit normal, an RGB
diffuse albedo and the raw material channels of the specular model (``render.py``).

``NeuralField`` is the paper's network (supplement §2.4): positional encoding of the pixel coordinate
(10 frequencies), an 8-layer ReLU MLP of width 256 with the input concatenated again at layer 4, a
normal head on the backbone, and a material head (one projection layer and 4 layers of width 128)
giving albedo and material channels.

``GridField`` is the ``fast`` design: the high-frequency unknowns (normal, albedo) are free
per-pixel parameters at frame resolution, started from the closed-form initialisation, and the
low-frequency ones (F0, roughness or basis weights) live on a grid at event resolution, bilinearly
interpolated to frame pixels — the degrees of freedom the paper assigns to each stream (main §1),
with no network to evaluate. Smoothness comes from the TV term instead of the MLP's spectral bias.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

FieldOutput = tuple[Tensor, Tensor, Tensor]
"""(normal (P, 3) unit, albedo (P, 3) ≥ 0 in units of the albedo scale, raw material channels (P, C))."""


def _unit(v: Tensor) -> Tensor:
    return v / torch.sqrt(torch.sum(v * v, dim=-1, keepdim=True) + 1e-12)


def positional_encoding(coords: Tensor, frequencies: int) -> Tensor:
    """(P, 2) coordinates in [−1, 1] → (P, 2 + 4·frequencies): the coordinate, then sin and cos of
    2^k·π·coordinate for k < frequencies."""
    scales = (2.0 ** torch.arange(frequencies, dtype=coords.dtype, device=coords.device)) * math.pi
    angles = (coords[:, :, None] * scales).reshape(coords.shape[0], -1)
    return torch.cat([coords, torch.sin(angles), torch.cos(angles)], dim=-1)


class NeuralField(nn.Module):
    """The paper's coordinate MLP: M(x; Θ) → n, ρ_d, β."""

    def __init__(
        self,
        coords: Tensor,
        material_channels: int,
        material_init: Tensor,
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
        self.layers = nn.ModuleList(
            nn.Linear(d_in if i == 0 else width + (d_in if i == skip else 0), width) for i in range(depth)
        )
        self.normal_head = nn.Linear(width, 3)
        material: list[nn.Module] = [nn.Linear(width, width)]
        for i in range(material_depth):
            material += [nn.Linear(width if i == 0 else material_width, material_width), nn.ReLU()]
        self.material = nn.Sequential(*material)
        self.material_out = nn.Linear(material_width, 3 + material_channels)
        with torch.no_grad():
            # Start facing the camera with albedo ≈ the scale and the specular model's initial material.
            self.normal_head.weight.mul_(0.1)
            self.normal_head.bias.copy_(torch.tensor([0.0, 0.0, 1.0]))
            self.material_out.weight.mul_(0.1)
            self.material_out.bias.copy_(torch.cat([torch.full((3,), math.log(math.e - 1.0)), material_init]))

    def forward(self, index: Tensor | None = None) -> FieldOutput:
        """The maps at the masked pixels ``index`` (all when None)."""
        x = self.encoded if index is None else self.encoded[index]
        h = x
        for i, layer in enumerate(self.layers):
            if i == self.skip:
                h = torch.cat([h, x], dim=-1)
            h = torch.relu(layer(h))
        normal = _unit(self.normal_head(h))
        out = self.material_out(self.material(h))
        return normal, nn.functional.softplus(out[:, :3]), out[:, 3:]


class GridField(nn.Module):
    """Per-pixel normal and albedo at frame resolution, material channels on the event grid."""

    def __init__(
        self,
        init_normal: Tensor,
        init_albedo: Tensor,
        grid_shape: tuple[int, int],
        taps: tuple[Tensor, Tensor],
        material_init: Tensor,
    ) -> None:
        super().__init__()
        self.normal = nn.Parameter(init_normal.clone())
        self.log_albedo = nn.Parameter(torch.log(torch.clamp(init_albedo, min=1e-3)))
        channels = material_init.shape[0]
        self.grid_shape = grid_shape
        self.grid = nn.Parameter(material_init[None, :].repeat(grid_shape[0] * grid_shape[1], 1).to(init_normal.dtype))
        self.register_buffer("tap_index", taps[0])
        self.register_buffer("tap_weight", taps[1].to(init_normal.dtype))
        self.channels = channels

    def grid_raw(self, index: Tensor | None = None) -> Tensor:
        """(P, C) raw material channels interpolated to the masked frame pixels ``index`` (all when None)."""
        taps, weights = (self.tap_index, self.tap_weight) if index is None else (self.tap_index[index], self.tap_weight[index])
        return torch.sum(self.grid[taps] * weights[..., None], dim=1)

    def forward(self, index: Tensor | None = None) -> FieldOutput:
        """The maps at the masked pixels ``index`` (all when None)."""
        if index is None:
            return _unit(self.normal), torch.exp(self.log_albedo), self.grid_raw()
        return _unit(self.normal[index]), torch.exp(self.log_albedo[index]), self.grid_raw(index)
