"""Reflectance models in torch, written once so the same function renders (simulator) and is
differentiated (solvers fitting normals and materials).

``shade(n, l, v, **maps)`` returns f_r(l, v)·[n·l]₊ per RGB channel with f_r = ρ_d + ρ_s and no 1/π on
the diffuse part (DualResPS eq. 3–4): a Lambertian pixel under a light of intensity e is e·ρ_d·n·l.
``n``, ``l`` and ``v`` are unit vectors (..., 3) in any broadcastable batch shape, on any device, float32
or float64; the maps broadcast against them. Pass exactly the maps named in the model's ``params``:

    brdf = GGX()
    rgb = brdf.shade(n, l, v, albedo=albedo, f0=f0, roughness=roughness)   # (..., 3)
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from typing import ClassVar

import torch
from torch import Tensor

from pstoolkit.options import Option

MIN_ROUGHNESS = 0.02
# Keeps the half vector's normalisation differentiable when l = −v (its length is then zero).
_HALF_EPS = 1e-12


def _dot(a: Tensor, b: Tensor) -> Tensor:
    return torch.sum(a * b, dim=-1, keepdim=True)


def _as_map(value: Tensor | float | tuple[float, ...], like: Tensor) -> Tensor:
    return torch.as_tensor(value, dtype=like.dtype, device=like.device)


def _channel_map(value: Tensor | float, like: Tensor) -> Tensor:
    """A one-channel map given as (...) or (..., 1), as (..., 1)."""
    tensor = _as_map(value, like)
    return tensor if tensor.dim() > 0 and tensor.shape[-1] == 1 else tensor.unsqueeze(-1)


class BRDF(ABC):
    """A reflectance model: ``name`` (registry name), ``summary`` (one line), ``params`` (the maps
    ``shade`` takes as keywords)."""

    name: ClassVar[str]
    summary: ClassVar[str]
    options: ClassVar[tuple[Option, ...]] = ()
    params: ClassVar[tuple[str, ...]]

    @abstractmethod
    def shade(self, n: Tensor, l: Tensor, v: Tensor, **maps: Tensor) -> Tensor:
        """f_r(l, v)·[n·l]₊ per RGB channel, shape broadcast(...) + (3,)."""


class Lambertian(BRDF):
    """Matte reflectance: ρ_d·[n·l]₊."""

    name: ClassVar[str] = "lambertian"
    summary: ClassVar[str] = "Lambertian diffuse reflectance with RGB albedo"
    params: ClassVar[tuple[str, ...]] = ("albedo",)

    def shade(self, n: Tensor, l: Tensor, v: Tensor, *, albedo: Tensor) -> Tensor:  # type: ignore[override]
        return _as_map(albedo, n) * torch.clamp(_dot(n, l), min=0.0)


class GGX(BRDF):
    """RGB diffuse albedo plus a Cook–Torrance/GGX specular lobe with constant RGB F0:
    ρ_s = D·F0·G / (4 (n·l)(n·v)), D = α²/(π((n·h)²(α²−1)+1)²) with α = r², G the Schlick-GGX product
    with k = (r+1)²/8. Roughness r is clamped to ≥ MIN_ROUGHNESS so D stays finite."""

    name: ClassVar[str] = "ggx"
    summary: ClassVar[str] = "RGB diffuse albedo plus GGX specular lobe (constant RGB F0, roughness)"
    params: ClassVar[tuple[str, ...]] = ("albedo", "f0", "roughness")

    def shade(self, n: Tensor, l: Tensor, v: Tensor, *, albedo: Tensor, f0: Tensor, roughness: Tensor) -> Tensor:  # type: ignore[override]
        r = torch.clamp(_channel_map(roughness, n), min=MIN_ROUGHNESS)
        alpha2 = r**4
        k = (r + 1.0) ** 2 / 8.0
        nl = torch.clamp(_dot(n, l), min=0.0)
        nv = torch.clamp(_dot(n, v), min=0.0)
        s = l + v
        ss = _dot(s, s)
        h = s / torch.sqrt(ss + _HALF_EPS)
        nh = _dot(n, h)
        # 1 − (n·h)² written as |n × h|² avoids cancellation near the peak, where float32 would round
        # the denominator of D to zero (or below) for smooth surfaces; the last term, 1 − |h|², is
        # negligible unless l = −v, where it keeps D finite.
        sin2 = torch.sum(torch.linalg.cross(*torch.broadcast_tensors(n, h), dim=-1) ** 2, dim=-1, keepdim=True) + _HALF_EPS / (ss + _HALF_EPS)
        d = alpha2 / (math.pi * (sin2 + nh * nh * alpha2) ** 2)
        # G/(4 n·l n·v) with Schlick-GGX G1(x) = x/(x(1−k)+k): the x factors cancel, leaving a form with
        # no division by n·l or n·v, finite (with finite gradients) at grazing angles.
        visibility = 1.0 / (4.0 * (nl * (1.0 - k) + k) * (nv * (1.0 - k) + k))
        specular = d * _as_map(f0, n) * visibility
        return (_as_map(albedo, n) + specular) * nl
