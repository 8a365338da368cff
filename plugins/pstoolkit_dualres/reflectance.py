"""A registered BRDF (``pstoolkit.optics.brdf``) as DualResPS fits it (supplement §2.3).

The BRDF's ``fit`` specification splits its maps into the per-pixel ones (``smooth`` False: the
diffuse albedo, the high-frequency unknowns the frames resolve) and the smooth materials (F0,
roughness …, the low-frequency unknowns the events constrain); a field (``fields``) produces raw
channels for each group and ``FitModel.maps`` maps them into their bounds: low + (high − low)·σ(raw)
for a bounded map, low + exp(raw) for one bounded below only. Radiometric maps are in units of the
capture's albedo scale (``problem.Problem.albedo_scale``), so every raw value stays O(1).

With ``indirect`` the model adds one smooth map of its own, ``INDIRECT``: light that reaches a pixel
from other parts of the object (inter-reflection) or the room, per unit of the light's intensity and
constant over a turn, which the pixel's diffuse albedo reflects like the direct light but which no
cast shadow removes (``forward_model``). It is not the BRDF's: ``shade`` never sees it.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from pstoolkit import BRDF, FitParam, UserError


def raw_value(param: FitParam, value: float) -> float:
    """The raw channel value whose activation is ``value`` (clipped into the open bounds)."""
    if param.high is None:
        return math.log(max(value - param.low, 1e-6))
    share = min(max((value - param.low) / (param.high - param.low), 1e-4), 1.0 - 1e-4)
    return math.log(share / (1.0 - share))


def activate(param: FitParam, raw: Tensor) -> Tensor:
    if param.high is None:
        return param.low + torch.exp(raw)
    return param.low + (param.high - param.low) * torch.sigmoid(raw)


INDIRECT = FitParam("indirect", 1, 0.0, None, 1e-3, radiometric=False, smooth=True)
"""The indirect irradiance b: per unit of the light's intensity, in the units of n·l (a surface facing
the light gets 1 from it directly), ≥ 0, starting almost at 0."""


def reflects_indirect(brdf: BRDF) -> bool:
    """Whether ``brdf`` has the per-pixel RGB diffuse albedo that reflects ``INDIRECT`` light."""
    return any(p.radiometric and p.channels == 3 and not p.smooth for p in brdf.fit)


class FitModel:
    """``brdf`` with its maps split into ``pixel`` and ``smooth`` parameters (in ``fit`` order), and
    with ``indirect`` the ``INDIRECT`` map last among the smooth ones. UserError for ``indirect`` with
    a BRDF that has no RGB diffuse albedo to reflect it."""

    def __init__(self, brdf: BRDF, indirect: bool = False) -> None:
        self.brdf = brdf
        self.pixel = tuple(p for p in brdf.fit if not p.smooth)
        self.smooth = tuple(p for p in brdf.fit if p.smooth) + ((INDIRECT,) if indirect else ())
        self.indirect = indirect
        self.pixel_channels = sum(p.channels for p in self.pixel)
        self.smooth_channels = sum(p.channels for p in self.smooth)
        diffuse = [p for p in self.pixel if p.radiometric and p.channels == 3]
        # the closed-form start gives an RGB albedo: it starts the first RGB reflectance per pixel
        self.diffuse = diffuse[0].name if diffuse else None
        if indirect and self.diffuse is None:
            raise UserError(f"dualres: BRDF {brdf.name!r} has no RGB diffuse albedo to reflect the indirect light (indirect=true)")

    @property
    def name(self) -> str:
        return self.brdf.name

    def parameters(self) -> list[nn.Parameter]:
        """Parameters shared by all pixels (a BRDF that is a torch module), fitted with the maps."""
        return list(self.brdf.parameters()) if isinstance(self.brdf, nn.Module) else []

    def to(self, device: torch.device | str) -> FitModel:
        if isinstance(self.brdf, nn.Module):
            self.brdf.to(device)
        return self

    def raw_init(self, group: str) -> Tensor:
        """(channels,) raw start values of the ``pixel`` or ``smooth`` group."""
        params = self.pixel if group == "pixel" else self.smooth
        values = [raw_value(p, p.init) for p in params for _ in range(p.channels)]
        return torch.tensor(values, dtype=torch.float32)

    def pixel_raw_from(self, albedo: Tensor) -> Tensor:
        """(P, pixel_channels) raw start values of the per-pixel maps, the diffuse one from ``albedo``
        (P, 3) (relative units) where the model has one."""
        out = self.raw_init("pixel").to(albedo.device, albedo.dtype).repeat(albedo.shape[0], 1)
        offset = 0
        for p in self.pixel:
            if p.name == self.diffuse:
                low = p.low
                out[:, offset : offset + 3] = torch.log(torch.clamp(albedo - low, min=1e-3)) if p.high is None else \
                    torch.logit(torch.clamp((albedo - low) / (p.high - low), 1e-4, 1 - 1e-4))
            offset += p.channels
        return out

    def maps(self, pixel_raw: Tensor, smooth_raw: Tensor) -> dict[str, Tensor]:
        """Every map of the BRDF, (P, channels) each, from the raw channels of the two groups."""
        out: dict[str, Tensor] = {}
        for params, raw in ((self.pixel, pixel_raw), (self.smooth, smooth_raw)):
            offset = 0
            for p in params:
                out[p.name] = activate(p, raw[..., offset : offset + p.channels])
                offset += p.channels
        return out

    def shade(self, n: Tensor, l: Tensor, v: Tensor, maps: dict[str, Tensor]) -> Tensor:
        """f_r·[n·l]₊ (..., 3) through the BRDF (the indirect map left out)."""
        return self.brdf.shade(n, l, v, **{name: value for name, value in maps.items() if name != INDIRECT.name})

    def indirect_light(self, maps: dict[str, Tensor]) -> Tensor | None:
        """(..., 3) the radiance ρ_d·b the indirect light gives per unit of light intensity, or None
        without ``indirect``."""
        if not self.indirect:
            return None
        return maps[self.diffuse] * maps[INDIRECT.name]
