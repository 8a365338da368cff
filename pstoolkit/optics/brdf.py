"""Reflectance models in torch, written once so the same function renders (simulator) and is
differentiated (solvers fitting normals and materials).

``shade(n, l, v, **maps)`` returns f_r(l, v)·[n·l]₊ per RGB channel with f_r = ρ_d + ρ_s and no 1/π on
the diffuse part (DualResPS eq. 3–4): a Lambertian pixel under a light of intensity e is e·ρ_d·n·l.
``n``, ``l`` and ``v`` are unit vectors (..., 3) in any broadcastable batch shape, on any device, float32
or float64; the maps broadcast against them. Pass exactly the maps named in the model's ``params``:

    brdf = GGX()
    rgb = brdf.shade(n, l, v, albedo=albedo, f0=f0, roughness=roughness)   # (..., 3)

A solver that fits a model reads its ``fit`` specification (``FitParam``: channels, bounds, start
value, whether the map scales with the light and whether it may change from pixel to pixel or is a
smooth material), and ``derived_maps`` for what the fitted maps imply in other workflows. A model
with parameters shared by all pixels (the learned bases of ``MLPBases``) is also a ``torch.nn.Module``
whose ``parameters()`` a solver fits with the maps.

Built in: ``lambertian``, ``ggx`` (the simulator's and DualResPS's model), and the specular models of
the DualResPS ablation (supplement Table 2): ``sg`` (spherical-Gaussian bases), ``mlp-bases`` (LL22a's
learned bases of n·h and v·h) and ``metallic`` (GGX with a metallic parameter instead of F0).
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import torch
from torch import Tensor, nn

from pstoolkit.optics.grey import GREY_WEIGHTS
from pstoolkit.plugin.options import Option

MIN_ROUGHNESS = 0.02
# Keeps the half vector's normalisation differentiable when l = −v (its length is then zero).
HALF_EPS = 1e-12
"""Added to |l + v|² before the half vector is normalised (l = −v leaves it undefined)."""


def _dot(a: Tensor, b: Tensor) -> Tensor:
    return torch.sum(a * b, dim=-1, keepdim=True)


def _as_map(value: Tensor | float | tuple[float, ...], like: Tensor) -> Tensor:
    return torch.as_tensor(value, dtype=like.dtype, device=like.device)


def _channel_map(value: Tensor | float, like: Tensor) -> Tensor:
    """A one-channel map given as (...) or (..., 1), as (..., 1)."""
    tensor = _as_map(value, like)
    return tensor if tensor.dim() > 0 and tensor.shape[-1] == 1 else tensor.unsqueeze(-1)


@dataclass(frozen=True)
class FitParam:
    """How a solver fits one map of a BRDF: ``channels`` per pixel, bounds ``low``..``high`` (None: no
    upper bound), ``init`` the start value, ``radiometric`` True for a reflectance that scales with
    the light and the exposure (fitted in units of a bright albedo of the capture, so its bounds and
    start are in those units too), ``smooth`` True for a material that varies slowly over the surface
    (the low-frequency unknowns of DualResPS that the events constrain), False for one that may
    change from pixel to pixel (the diffuse albedo)."""

    name: str
    channels: int
    low: float
    high: float | None
    init: float
    radiometric: bool
    smooth: bool


class BRDF(ABC):
    """A reflectance model: ``name`` (registry name), ``summary`` (one line), ``params`` (the maps
    ``shade`` takes as keywords) and ``fit`` (how a solver fits each of them, in ``params`` order)."""

    name: ClassVar[str]
    summary: ClassVar[str]
    options: ClassVar[tuple[Option, ...]] = ()
    params: ClassVar[tuple[str, ...]]
    fit: ClassVar[tuple[FitParam, ...]]

    @abstractmethod
    def shade(self, n: Tensor, l: Tensor, v: Tensor, **maps: Tensor) -> Tensor:
        """f_r(l, v)·[n·l]₊ per RGB channel, with no 1/π on the diffuse part (DualResPS eq. 3–4).

        Parameters
        ----------
        n, l, v
            Unit normal, unit direction to the light and unit direction to the viewer, (..., 3) in any
            broadcastable batch shape, float32 or float64, on any device.
        **maps
            Exactly the maps named in ``params``, as keywords, broadcasting against ``n``: (...,
            channels) with the channels of ``fit``; a one-channel map may also be given as (...), and a
            number as a constant map.

        Returns
        -------
        Tensor
            broadcast(...) + (3,): the reflected radiance per RGB channel under a light of intensity 1
            (a Lambertian pixel under a light of intensity e is e·ρ_d·n·l).
        """

    def derived_maps(self, maps: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Maps implied by fitted ``maps`` (each (..., channels), radiometric ones relative to a bright
        albedo) in other workflows; none by default."""
        return {}


ALBEDO = FitParam("albedo", 3, 0.0, None, 1.0, radiometric=True, smooth=False)
ROUGHNESS = FitParam("roughness", 1, MIN_ROUGHNESS, 1.0, 0.5, radiometric=False, smooth=True)
# Largest specular colour, in units of a bright albedo: metals reflect more than a bright diffuse one.
F0_MAX = 2.0
DIELECTRIC_F0 = 0.04
BASES = 9
# Sharpness of the spherical-Gaussian bases: from a broad sheen to a near-mirror lobe.
SG_SHARPNESS = tuple(float(x) for x in np.geomspace(4.0, 1000.0, BASES))
# (n·h, v·h) nodes of the tabulated learned bases: fine in n·h, where highlights are sharp.
BASIS_TABLE = (256, 32)


class Lambertian(BRDF):
    """Matte reflectance: ρ_d·[n·l]₊."""

    name: ClassVar[str] = "lambertian"
    summary: ClassVar[str] = "Lambertian diffuse reflectance with RGB albedo"
    params: ClassVar[tuple[str, ...]] = ("albedo",)
    fit: ClassVar[tuple[FitParam, ...]] = (ALBEDO,)

    def shade(self, n: Tensor, l: Tensor, v: Tensor, *, albedo: Tensor) -> Tensor:  # type: ignore[override]
        return _as_map(albedo, n) * torch.clamp(_dot(n, l), min=0.0)


class GGX(BRDF):
    """RGB diffuse albedo plus a Cook–Torrance/GGX specular lobe with constant RGB F0:
    ρ_s = D·F0·G / (4 (n·l)(n·v)), D = α²/(π((n·h)²(α²−1)+1)²) with α = r², G the Schlick-GGX product
    with k = (r+1)²/8. Roughness r is clamped to ≥ MIN_ROUGHNESS so D stays finite."""

    name: ClassVar[str] = "ggx"
    summary: ClassVar[str] = "RGB diffuse albedo plus GGX specular lobe (constant RGB F0, roughness)"
    params: ClassVar[tuple[str, ...]] = ("albedo", "f0", "roughness")
    fit: ClassVar[tuple[FitParam, ...]] = (
        ALBEDO, FitParam("f0", 3, 0.0, F0_MAX, 0.1, radiometric=True, smooth=True), ROUGHNESS,
    )

    def shade(self, n: Tensor, l: Tensor, v: Tensor, *, albedo: Tensor, f0: Tensor, roughness: Tensor) -> Tensor:  # type: ignore[override]
        """(ρ_d + ρ_s)·[n·l]₊ per RGB channel; see ``BRDF.shade`` for ``n``, ``l``, ``v`` and the result.

        Parameters
        ----------
        albedo
            (..., 3) diffuse albedo ρ_d.
        f0
            (..., 3) specular colour F0.
        roughness
            (...) or (..., 1) roughness r, clamped to ≥ ``MIN_ROUGHNESS``.
        """
        r = torch.clamp(_channel_map(roughness, n), min=MIN_ROUGHNESS)
        alpha2 = r**4
        k = (r + 1.0) ** 2 / 8.0
        nl = torch.clamp(_dot(n, l), min=0.0)
        nv = torch.clamp(_dot(n, v), min=0.0)
        s = l + v
        ss = _dot(s, s)
        h = s / torch.sqrt(ss + HALF_EPS)
        nh = _dot(n, h)
        # 1 − (n·h)² written as |n × h|² avoids cancellation near the peak, where float32 would round
        # the denominator of D to zero (or below) for smooth surfaces; the last term, 1 − |h|², is
        # negligible unless l = −v, where it keeps D finite.
        sin2 = torch.sum(torch.linalg.cross(*torch.broadcast_tensors(n, h), dim=-1) ** 2, dim=-1, keepdim=True) + HALF_EPS / (ss + HALF_EPS)
        d = alpha2 / (math.pi * (sin2 + nh * nh * alpha2) ** 2)
        # G/(4 n·l n·v) with Schlick-GGX G1(x) = x/(x(1−k)+k): the x factors cancel, leaving a form with
        # no division by n·l or n·v, finite (with finite gradients) at grazing angles.
        visibility = 1.0 / (4.0 * (nl * (1.0 - k) + k) * (nv * (1.0 - k) + k))
        specular = d * _as_map(f0, n) * visibility
        return (_as_map(albedo, n) + specular) * nl

    def derived_maps(self, maps: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """``metallic`` and ``base_color`` of the metal-roughness workflow (``pbr_from_specular``)."""
        metallic, base = pbr_from_specular(maps["albedo"], maps["f0"])
        return {"metallic": metallic, "base_color": base}


def pbr_from_specular(albedo: np.ndarray, f0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Metallic (...) and base colour (..., 3) from diffuse albedo and specular colour F0, both
    relative reflectances in [0, 1] (the specular-glossiness → metal-roughness conversion of glTF's
    KHR_materials_pbrSpecularGlossiness, DualResPS supplement §4.2)."""

    def brightness(c: np.ndarray) -> np.ndarray:
        return np.sqrt(np.tensordot(c * c, np.array(GREY_WEIGHTS), axes=([-1], [0])))

    diffuse = np.clip(albedo, 0.0, 1.0)
    specular = np.clip(f0, 0.0, 1.0)
    max_specular = specular.max(axis=-1)
    perceived_diffuse = brightness(diffuse)
    perceived_specular = brightness(specular)
    a = DIELECTRIC_F0
    b = perceived_diffuse * (1.0 - max_specular) / (1.0 - a) + perceived_specular - 2.0 * a
    c = a - perceived_specular
    root = (-b + np.sqrt(np.maximum(b * b - 4.0 * a * c, 0.0))) / (2.0 * a)
    metallic = np.where(perceived_specular < a, 0.0, np.clip(root, 0.0, 1.0))
    m = metallic[..., None]
    from_diffuse = diffuse * ((1.0 - max_specular) / (1.0 - a))[..., None] / np.maximum(1.0 - m, 1e-4)
    from_specular = (specular - a * (1.0 - m)) / np.maximum(m, 1e-4)
    base = np.clip(from_diffuse + (from_specular - from_diffuse) * m * m, 0.0, 1.0)
    return metallic, base


class MetallicGGX(BRDF):
    """GGX in the metal-roughness workflow: base colour b and metallic m give the diffuse albedo
    (1 − m)·b and F0 = (1 − m)·0.04 + m·b (supplement Table 2, "w/ metallic ρ_s")."""

    name: ClassVar[str] = "metallic"
    summary: ClassVar[str] = "GGX with base colour and metallic instead of diffuse albedo and F0 (metal-roughness)"
    params: ClassVar[tuple[str, ...]] = ("base_color", "metallic", "roughness")
    fit: ClassVar[tuple[FitParam, ...]] = (
        FitParam("base_color", 3, 0.0, None, 1.0, radiometric=True, smooth=False),
        FitParam("metallic", 1, 0.0, 1.0, 0.05, radiometric=False, smooth=True),
        ROUGHNESS,
    )

    @staticmethod
    def _split(base_color: Tensor, metallic: Tensor, like: Tensor) -> tuple[Tensor, Tensor]:
        m = _channel_map(metallic, like)
        base = _as_map(base_color, like)
        return (1.0 - m) * base, (1.0 - m) * DIELECTRIC_F0 + m * base

    def shade(self, n: Tensor, l: Tensor, v: Tensor, *, base_color: Tensor, metallic: Tensor, roughness: Tensor) -> Tensor:  # type: ignore[override]
        """``GGX.shade`` with albedo (1 − m)·b and F0 = (1 − m)·0.04 + m·b; see ``BRDF.shade`` for ``n``,
        ``l``, ``v`` and the result.

        Parameters
        ----------
        base_color
            (..., 3) base colour b.
        metallic
            (...) or (..., 1) metallic m, in [0, 1].
        roughness
            (...) or (..., 1) roughness r, clamped to ≥ ``MIN_ROUGHNESS``.
        """
        albedo, f0 = self._split(base_color, metallic, n)
        return _GGX.shade(n, l, v, albedo=albedo, f0=f0, roughness=roughness)

    def derived_maps(self, maps: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """The diffuse ``albedo`` and ``f0`` of the specular workflow."""
        m = maps["metallic"][..., None] if maps["metallic"].ndim == maps["base_color"].ndim - 1 else maps["metallic"]
        return {"albedo": (1.0 - m) * maps["base_color"], "f0": (1.0 - m) * DIELECTRIC_F0 + m * maps["base_color"]}


class _SpecularBases(BRDF):
    """Diffuse albedo plus tint·Σ_b w_b·basis_b(n, l, v), times [n·l]₊: 9 non-negative weights per
    pixel and an RGB tint, both smooth materials."""

    params: ClassVar[tuple[str, ...]] = ("albedo", "basis_weights", "specular_tint")
    fit: ClassVar[tuple[FitParam, ...]] = (
        ALBEDO,
        FitParam("basis_weights", BASES, 0.0, None, 0.02, radiometric=False, smooth=True),
        FitParam("specular_tint", 3, 0.0, F0_MAX, 1.0, radiometric=True, smooth=True),
    )

    @abstractmethod
    def bases(self, n: Tensor, l: Tensor, v: Tensor) -> Tensor:
        """(..., BASES) basis values."""

    def shade(self, n: Tensor, l: Tensor, v: Tensor, *, albedo: Tensor, basis_weights: Tensor, specular_tint: Tensor) -> Tensor:  # type: ignore[override]
        """(ρ_d + tint·Σ_b w_b·basis_b(n, l, v))·[n·l]₊ per RGB channel; see ``BRDF.shade`` for ``n``,
        ``l``, ``v`` and the result.

        Parameters
        ----------
        albedo
            (..., 3) diffuse albedo ρ_d.
        basis_weights
            (..., ``BASES``) non-negative weights w_b of the specular bases.
        specular_tint
            (..., 3) RGB tint of the specular term.
        """
        specular = _as_map(specular_tint, n) * _dot(_as_map(basis_weights, n), self.bases(n, l, v))
        return (_as_map(albedo, n) + specular) * torch.clamp(_dot(n, l), min=0.0)


def _half(l: Tensor, v: Tensor) -> Tensor:
    s = l + v
    return s / torch.sqrt(_dot(s, s) + HALF_EPS)


class SphericalGaussians(_SpecularBases):
    """Specular bases exp(λ_b (n·h − 1)) of fixed sharpness λ_b from a broad sheen to a near mirror."""

    name: ClassVar[str] = "sg"
    summary: ClassVar[str] = "diffuse albedo plus 9 spherical-Gaussian specular bases with per-pixel weights and an RGB tint"

    def bases(self, n: Tensor, l: Tensor, v: Tensor) -> Tensor:
        sharpness = torch.as_tensor(SG_SHARPNESS, dtype=n.dtype, device=n.device)
        return torch.exp(sharpness * (_dot(n, _half(l, v)) - 1.0))


class MLPBases(_SpecularBases, nn.Module):
    """LL22a's specular bases: 9 non-negative functions of (n·h, v·h) from a small MLP whose weights
    are fitted with the maps. The bases depend on those two numbers in [0, 1] only, so the MLP is
    evaluated on a ``BASIS_TABLE`` grid of them per call and the samples interpolate it bilinearly
    (gradients reach the MLP through the table): one small pass instead of one per sample."""

    name: ClassVar[str] = "mlp-bases"
    summary: ClassVar[str] = "diffuse albedo plus 9 specular bases of (n·h, v·h) learned by a small MLP (LL22a)"

    def __init__(self, width: int = 64) -> None:
        nn.Module.__init__(self)
        self.net = nn.Sequential(nn.Linear(2, width), nn.ReLU(), nn.Linear(width, width), nn.ReLU(),
                                 nn.Linear(width, BASES), nn.Softplus())
        nh, vh = (torch.linspace(0.0, 1.0, k) for k in BASIS_TABLE)
        self.register_buffer("nodes", torch.stack(torch.meshgrid(nh, vh, indexing="ij"), dim=-1).reshape(-1, 2))

    def bases(self, n: Tensor, l: Tensor, v: Tensor) -> Tensor:
        h = _half(l, v)
        nh, vh = torch.broadcast_tensors(_dot(n, h)[..., 0], _dot(v, h)[..., 0])
        table = self.net(self.nodes.to(n.device)).to(n.dtype)  # (rows·cols, BASES), n·h major
        rows, cols = BASIS_TABLE
        x = torch.clamp(nh, 0.0, 1.0) * (rows - 1)
        y = torch.clamp(vh, 0.0, 1.0) * (cols - 1)
        x0 = torch.clamp(torch.floor(x.detach()), max=rows - 2)
        y0 = torch.clamp(torch.floor(y.detach()), max=cols - 2)
        fx, fy = (x - x0)[..., None], (y - y0)[..., None]
        corner = (x0 * cols + y0).long()
        return ((1 - fx) * (1 - fy) * table[corner] + (1 - fx) * fy * table[corner + 1]
                + fx * (1 - fy) * table[corner + cols] + fx * fy * table[corner + cols + 1])


_GGX = GGX()
BRDFS: tuple[type[BRDF], ...] = (Lambertian, GGX, SphericalGaussians, MLPBases, MetallicGGX)
"""The built-in models, registered by the ``core`` plugin."""
