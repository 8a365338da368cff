"""The ``blinn-phong`` BRDF: diffuse albedo plus a white Blinn-Phong lobe k_s·(n·h)^s, shaded by
[n·l]₊ as every pstoolkit BRDF (no 1/π on the diffuse part).

``shade`` is written once in torch, so the simulator can render with it and solvers differentiate
it; ``fit`` tells a solver (``dualres --set brdf=blinn-phong``) how to fit each map: its channels,
bounds and start value, whether it scales with the light (``radiometric``) and whether it may change
from pixel to pixel or is a smooth material.
"""

from __future__ import annotations

from typing import ClassVar

import torch
from torch import Tensor

from pstoolkit import BRDF, FitParam


class BlinnPhong(BRDF):
    name: ClassVar[str] = "blinn-phong"
    summary: ClassVar[str] = "diffuse albedo plus a white Blinn-Phong lobe (strength, shininess)"
    params: ClassVar[tuple[str, ...]] = ("albedo", "specular", "shininess")
    fit: ClassVar[tuple[FitParam, ...]] = (
        FitParam("albedo", 3, 0.0, None, 1.0, radiometric=True, smooth=False),
        FitParam("specular", 1, 0.0, 4.0, 0.1, radiometric=True, smooth=True),
        FitParam("shininess", 1, 1.0, 1000.0, 50.0, radiometric=False, smooth=True),
    )

    def shade(self, n: Tensor, l: Tensor, v: Tensor, *, albedo: Tensor, specular: Tensor, shininess: Tensor) -> Tensor:  # type: ignore[override]
        h = l + v
        h = h / torch.sqrt(torch.sum(h * h, dim=-1, keepdim=True) + 1e-12)
        nh = torch.clamp(torch.sum(n * h, dim=-1, keepdim=True), min=0.0)
        nl = torch.clamp(torch.sum(n * l, dim=-1, keepdim=True), min=0.0)
        lobe = torch.as_tensor(specular, dtype=n.dtype) * nh ** torch.as_tensor(shininess, dtype=n.dtype)
        return (torch.as_tensor(albedo, dtype=n.dtype) + lobe) * nl
