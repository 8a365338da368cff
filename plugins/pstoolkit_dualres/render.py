"""Differentiable rendering of DualResPS (eq. 21–22): irradiance Ĩ(x, t) = e(t)·f̃_r·m_c·[l(t)·ñ]₊,
frames as Σ Ĩ·Δt per (frame, pixel) — at the per-pixel importance samples of preprocessing
(``frame_prediction``) or on a time grid shared by all pixels (``frame_prediction_grid``) — and the
grey irradiance of event super pixels as the area average of the frame pixels under them.

The specular term is one of four models (supplement Table 2), each turning the raw material channels
of the field (``model.py``) into reflectance:

- ``ggx`` (default): constant RGB F0 (sigmoid) and roughness (sigmoid) in ``pstoolkit.brdf.GGX``;
- ``metallic``: the field's RGB albedo is the base colour, a metallic channel m mixes diffuse
  (1 − m)·base and F0 = (1 − m)·0.04 + m·base;
- ``sg``: a sum of 9 spherical Gaussians exp(λ_b (n·h − 1)) with fixed sharpness λ_b, per-pixel
  weights (softplus) and an RGB tint;
- ``mlp``: LL22a's specular bases, 9 functions of (n·h, v·h) from a small shared MLP (tabulated on a
  grid of the two and interpolated), weighted per pixel like ``sg``.

Albedo and F0 are relative: in units of the albedo scale of the capture (a bright albedo, see
``train.albedo_scale``), which the frame weights carry, so that every parameter stays O(1).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import ClassVar

import numpy as np
import torch
from torch import Tensor, nn

from pstoolkit.brdf import GGX
from pstoolkit.render import GREY_WEIGHTS

DIELECTRIC_F0 = 0.04
# Largest specular colour, in units of the albedo scale: metals reflect more than a bright diffuse albedo.
F0_MAX = 2.0
BASES = 9
# Sharpness of the spherical-Gaussian bases: from a broad sheen to a near-mirror lobe.
SG_SHARPNESS = tuple(float(x) for x in np.geomspace(4.0, 1000.0, BASES))
# (n·h, v·h) nodes of the tabulated MLP bases: fine in n·h, where highlights are sharp.
TABLE_SHAPE = (256, 32)
_GGX = GGX()


def _dot(a: Tensor, b: Tensor) -> Tensor:
    return torch.sum(a * b, dim=-1, keepdim=True)


def _half(l: Tensor, v: Tensor) -> Tensor:
    s = l + v
    return s / torch.sqrt(_dot(s, s) + 1e-12)


class Reflectance(nn.Module, ABC):
    """A specular model: ``channels`` raw material channels per pixel, ``raw_init`` their start values,
    ``shade`` = f_r·[n·l]₊ per RGB channel, ``maps`` the named output maps."""

    name: ClassVar[str]
    channels: ClassVar[int]

    @abstractmethod
    def raw_init(self) -> Tensor:
        """(channels,) start values of the raw material channels: a weak, broad highlight."""

    @abstractmethod
    def shade(self, n: Tensor, l: Tensor, v: Tensor, albedo: Tensor, raw: Tensor) -> Tensor:
        """(..., 3) f_r·[n·l]₊ for unit n, l, v (..., 3), RGB albedo (..., 3) and raw channels."""

    @abstractmethod
    def maps(self, albedo: Tensor, raw: Tensor) -> dict[str, Tensor]:
        """The per-pixel maps the solver reports (``albedo`` = diffuse ρ_d, ``f0``, ``roughness`` …)."""


class GGXReflectance(Reflectance):
    name: ClassVar[str] = "ggx"
    channels: ClassVar[int] = 4

    def raw_init(self) -> Tensor:
        return torch.tensor([-3.0, -3.0, -3.0, 0.0])

    def _params(self, raw: Tensor) -> tuple[Tensor, Tensor]:
        return F0_MAX * torch.sigmoid(raw[..., :3]), torch.sigmoid(raw[..., 3:4])

    def shade(self, n: Tensor, l: Tensor, v: Tensor, albedo: Tensor, raw: Tensor) -> Tensor:
        f0, roughness = self._params(raw)
        return _GGX.shade(n, l, v, albedo=albedo, f0=f0, roughness=roughness)

    def maps(self, albedo: Tensor, raw: Tensor) -> dict[str, Tensor]:
        f0, roughness = self._params(raw)
        return {"albedo": albedo, "f0": f0, "roughness": roughness[..., 0]}


class MetallicReflectance(Reflectance):
    name: ClassVar[str] = "metallic"
    channels: ClassVar[int] = 2

    def raw_init(self) -> Tensor:
        return torch.tensor([-3.0, 0.0])

    def _params(self, albedo: Tensor, raw: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        metallic = torch.sigmoid(raw[..., 0:1])
        roughness = torch.sigmoid(raw[..., 1:2])
        diffuse = (1.0 - metallic) * albedo
        f0 = (1.0 - metallic) * DIELECTRIC_F0 + metallic * albedo
        return diffuse, f0, roughness, metallic

    def shade(self, n: Tensor, l: Tensor, v: Tensor, albedo: Tensor, raw: Tensor) -> Tensor:
        diffuse, f0, roughness, _ = self._params(albedo, raw)
        return _GGX.shade(n, l, v, albedo=diffuse, f0=f0, roughness=roughness)

    def maps(self, albedo: Tensor, raw: Tensor) -> dict[str, Tensor]:
        diffuse, f0, roughness, metallic = self._params(albedo, raw)
        return {"albedo": diffuse, "f0": f0, "roughness": roughness[..., 0], "metallic": metallic[..., 0],
                "base_color": albedo}


class _BasisReflectance(Reflectance):
    """Specular = tint·Σ_b w_b·basis_b(n, l, v): raw channels are 9 weights then an RGB tint."""

    channels: ClassVar[int] = BASES + 3

    def raw_init(self) -> Tensor:
        return torch.cat([torch.full((BASES,), -4.0), torch.zeros(3)])

    @abstractmethod
    def bases(self, n: Tensor, l: Tensor, v: Tensor) -> Tensor:
        """(..., BASES) basis values."""

    def shade(self, n: Tensor, l: Tensor, v: Tensor, albedo: Tensor, raw: Tensor) -> Tensor:
        weights = nn.functional.softplus(raw[..., :BASES])
        tint = F0_MAX * torch.sigmoid(raw[..., BASES:])
        specular = tint * _dot(weights, self.bases(n, l, v))
        return (albedo + specular) * torch.clamp(_dot(n, l), min=0.0)

    def maps(self, albedo: Tensor, raw: Tensor) -> dict[str, Tensor]:
        return {"albedo": albedo, "specular_tint": F0_MAX * torch.sigmoid(raw[..., BASES:])}


class SGReflectance(_BasisReflectance):
    name: ClassVar[str] = "sg"

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("sharpness", torch.tensor(SG_SHARPNESS))

    def bases(self, n: Tensor, l: Tensor, v: Tensor) -> Tensor:
        nh = _dot(n, _half(l, v))
        return torch.exp(self.sharpness.to(nh.dtype) * (nh - 1.0))


class MLPReflectance(_BasisReflectance):
    """LL22a's bases: a small MLP of (n·h, v·h). The bases depend on those two numbers in [0, 1]
    only, so the MLP is evaluated once per step on a ``TABLE_SHAPE`` grid of them and the samples
    interpolate it bilinearly (gradients reach the MLP through the table): on the fast preset's
    frame grid at 256 px that is one MLP pass on 8 192 nodes instead of ~1.2 M samples."""

    name: ClassVar[str] = "mlp"

    def __init__(self, width: int = 64) -> None:
        super().__init__()
        self.net = nn.Sequential(nn.Linear(2, width), nn.ReLU(), nn.Linear(width, width), nn.ReLU(),
                                 nn.Linear(width, BASES), nn.Softplus())
        nh, vh = (torch.linspace(0.0, 1.0, k) for k in TABLE_SHAPE)
        self.register_buffer("nodes", torch.stack(torch.meshgrid(nh, vh, indexing="ij"), dim=-1).reshape(-1, 2))

    def bases(self, n: Tensor, l: Tensor, v: Tensor) -> Tensor:
        h = _half(l, v)
        nh, vh = torch.broadcast_tensors(_dot(n, h)[..., 0], _dot(v, h)[..., 0])
        table = self.net(self.nodes).to(n.dtype)  # (rows·cols, BASES), n·h major
        rows, cols = TABLE_SHAPE
        x = torch.clamp(nh, 0.0, 1.0) * (rows - 1)
        y = torch.clamp(vh, 0.0, 1.0) * (cols - 1)
        x0 = torch.clamp(torch.floor(x.detach()), max=rows - 2)
        y0 = torch.clamp(torch.floor(y.detach()), max=cols - 2)
        fx, fy = (x - x0)[..., None], (y - y0)[..., None]
        corner = (x0 * cols + y0).long()
        return ((1 - fx) * (1 - fy) * table[corner] + (1 - fx) * fy * table[corner + 1]
                + fx * (1 - fy) * table[corner + cols] + fx * fy * table[corner + cols + 1])


REFLECTANCES: dict[str, type[Reflectance]] = {
    cls.name: cls for cls in (GGXReflectance, SGReflectance, MLPReflectance, MetallicReflectance)
}


def frame_prediction(
    reflectance: Reflectance,
    normal: Tensor,
    albedo: Tensor,
    raw: Tensor,
    sample_pixel: Tensor,
    sample_group: Tensor,
    light: Tensor,
    weight: Tensor,
    view: Tensor,
    groups: int,
) -> Tensor:
    """(groups, 3) frame values Σ_samples f_r·[n·l]₊·(e·m_c·Δt): ``sample_pixel`` (M,) indexes the
    per-pixel ``normal``/``albedo``/``raw``, ``sample_group`` (M,) = frame·P + pixel, ``light`` (M, 3)
    unit directions, ``weight`` (M, 3) RGB intensity × cast-shadow mask × Δt."""
    shaded = reflectance.shade(normal[sample_pixel], light, view, albedo[sample_pixel], raw[sample_pixel])
    out = torch.zeros((groups, 3), dtype=shaded.dtype, device=shaded.device)
    return out.index_add_(0, sample_group, shaded * weight)


def frame_prediction_grid(
    reflectance: Reflectance,
    normal: Tensor,
    albedo: Tensor,
    raw: Tensor,
    light: Tensor,
    weight: Tensor,
    visible: Tensor | None,
    view: Tensor,
    frames: int,
) -> Tensor:
    """(frames·P, 3) frame values on a time grid shared by all pixels: ``light`` (S, 3) and ``weight``
    (S, 3) (intensity × Δt) of S = frames × S_f samples in frame order, ``visible`` (P, S) the
    cast-shadow mask or None. Broadcasting (P, 1) pixels against (1, S) samples needs no gather or
    scatter, several times faster than ``frame_prediction`` for the same number of samples."""
    p, s = normal.shape[0], light.shape[0]
    shaded = reflectance.shade(normal[:, None, :], light[None], view, albedo[:, None, :], raw[:, None, :]) * weight
    if visible is not None:
        shaded = shaded * visible[..., None]
    return shaded.reshape(p, frames, s // frames, 3).sum(dim=2).transpose(0, 1).reshape(frames * p, 3)


def superpixel_grey(
    reflectance: Reflectance,
    normal: Tensor,
    albedo: Tensor,
    raw: Tensor,
    tap_pixel: Tensor,
    tap_weight: Tensor,
    light: Tensor,
    grey_intensity: Tensor,
    view: Tensor,
) -> Tensor:
    """(E,) grey irradiance of event super pixels: Σ_taps area weight × grey(f_r·[n·l]₊·e) over the
    frame pixels ``tap_pixel`` (E, F) under each, at one light (E, 3) per row; ``grey_intensity``
    (E, 3) is e_c times the Rec. 601 weight of channel c."""
    e, f = tap_pixel.shape
    flat = tap_pixel.reshape(-1)
    l = light[:, None, :].expand(e, f, 3).reshape(-1, 3)
    shaded = reflectance.shade(normal[flat], l, view, albedo[flat], raw[flat]).reshape(e, f, 3)
    return torch.sum(torch.sum(shaded * grey_intensity[:, None, :], dim=-1) * tap_weight, dim=-1)


def pbr_from_specular(albedo: np.ndarray, f0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Metallic (H, W) and base colour (H, W, 3) from diffuse albedo and specular colour F0, both
    relative reflectances in [0, 1] (the specular-glossiness → metal-roughness conversion of glTF's
    KHR_materials_pbrSpecularGlossiness, supplement §4.2)."""

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
