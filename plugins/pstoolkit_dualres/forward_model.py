"""Differentiable rendering of DualResPS (eq. 21–22): irradiance Ĩ(x, t) = e(t)·f̃_r·m_c·[l(t)·ñ]₊
through a fitted BRDF (``reflectance.FitModel``); frames as Σ Ĩ·Δt per (frame, pixel) — at the
per-pixel importance samples of preprocessing (``frame_prediction``) or on a time grid shared by all
pixels (``frame_prediction_grid``) — and the grey irradiance of event super pixels as the weighted
sum of the frame pixels under them (``superpixel_grey``).

A model with indirect light adds to each frame value ρ_d·b·∫e dt over the frame's window (``energy``,
``FitModel.indirect_light``): light from the rest of the object, which a cast shadow of the direct
light does not take away.
"""

from __future__ import annotations

import torch
from torch import Tensor

from pstoolkit_dualres.reflectance import INDIRECT, FitModel

Maps = dict[str, Tensor]


def _take(maps: Maps, index: Tensor) -> Maps:
    return {name: value[index] for name, value in maps.items()}


def shade_rows(model: FitModel, normal: Tensor, maps: Maps, pixel: Tensor, light: Tensor, view: Tensor) -> Tensor:
    """(N, 3) f_r·[n·l]₊ of the pixels ``pixel`` (N,) (rows of ``normal`` (P, 3) and ``maps``) under the
    unit directions ``light`` (N, 3): the rendering ``frame_prediction`` and ``superpixel_grey`` sum, which
    a caller may do once for both (``shaded``)."""
    return model.shade(normal[pixel], light, view, _take(maps, pixel))


def frame_prediction(model: FitModel, normal: Tensor, maps: Maps, sample_pixel: Tensor, sample_group: Tensor,
                     light: Tensor, weight: Tensor, view: Tensor, groups: int, energy: Tensor | None = None,
                     shaded: Tensor | None = None) -> Tensor:
    """Frame values Σ_samples f_r·[n·l]₊·(e·m_c·Δt) at per-pixel importance samples (eq. 21–22).

    Parameters
    ----------
    model
        The fitted BRDF.
    normal
        (P, 3) unit normals of the pixels.
    maps
        The BRDF's maps by name, (P, channels) each.
    sample_pixel
        (M,) int64: each sample's pixel, an index into ``normal`` and ``maps``.
    sample_group
        (M,) int64: each sample's output row, frame·P + pixel.
    light
        (M, 3) unit directions to the light.
    weight
        (M, 3) RGB intensity × lit × Δt of each sample.
    view
        (3,) unit direction to the camera.
    groups
        Number of output rows (frames·P).
    energy
        (K, 3) each frame's light energy, for a model with indirect light.
    shaded
        (M, 3) ``shade_rows`` of the samples, where the caller rendered them (None: rendered here).

    Returns
    -------
    Tensor
        (groups, 3) predicted frame values.
    """
    if shaded is None:
        shaded = shade_rows(model, normal, maps, sample_pixel, light, view)
    out = torch.zeros((groups, 3), dtype=shaded.dtype, device=shaded.device)
    out = out.index_add_(0, sample_group, shaded * weight)
    return _with_indirect(model, maps, out, energy)


def _with_indirect(model: FitModel, maps: Maps, frames_p: Tensor, energy: Tensor | None) -> Tensor:
    """``frames_p`` (K·P, 3) plus ρ_d·b·energy_k of a model with indirect light (unchanged without)."""
    indirect = model.indirect_light(maps)
    if indirect is None:
        return frames_p
    assert energy is not None, "a model with indirect light needs the frames' energy"
    k = energy.shape[0]
    return frames_p + (energy[:, None, :] * indirect[None]).reshape(k * indirect.shape[0], 3)


def frame_prediction_grid(model: FitModel, normal: Tensor, maps: Maps, light: Tensor, weight: Tensor,
                          visible: Tensor | None, view: Tensor, frames: int, energy: Tensor | None = None) -> Tensor:
    """Frame values on a time grid shared by all pixels. Broadcasting (P, 1) pixels against (1, S)
    samples needs no gather or scatter.

    Parameters
    ----------
    model
        The fitted BRDF.
    normal
        (P, 3) unit normals of the pixels.
    maps
        The BRDF's maps by name, (P, channels) each.
    light
        (S, 3) unit directions to the light of S = frames × S_f samples, in frame order.
    weight
        (S, 3) RGB intensity × Δt of each sample.
    visible
        (S, P) the lit share of each sample, or None (all lit).
    view
        (3,) unit direction to the camera.
    frames
        Number of frames K; must divide S.
    energy
        (K, 3) each frame's light energy, for a model with indirect light.

    Returns
    -------
    Tensor
        (frames·P, 3) predicted frame values, rows frame·P + pixel.
    """
    p, s = normal.shape[0], light.shape[0]
    shaded = model.shade(normal[:, None, :], light[None], view, {k: v[:, None, :] for k, v in maps.items()}) * weight
    if visible is not None:
        shaded = shaded * visible.T[..., None]
    direct = shaded.reshape(p, frames, s // frames, 3).sum(dim=2).transpose(0, 1).reshape(frames * p, 3)
    return _with_indirect(model, maps, direct, energy)


def superpixel_grey(model: FitModel, normal: Tensor, maps: Maps, tap_pixel: Tensor, tap_weight: Tensor,
                    light: Tensor, grey_intensity: Tensor, view: Tensor, tap_area: Tensor | None = None,
                    shaded: Tensor | None = None) -> Tensor:
    """Grey irradiance of event super pixels: Σ_taps weight × grey(f_r·[n·l]₊·e) over the frame pixels
    under each, at one light per row; with indirect light plus Σ_taps area × grey(ρ_d·b·e).

    Parameters
    ----------
    model
        The fitted BRDF.
    normal
        (P, 3) unit normals of the pixels.
    maps
        The BRDF's maps by name, (P, channels) each.
    tap_pixel
        (E, F) int64: the frame pixels under each super pixel, indices into ``normal`` and ``maps``.
    tap_weight
        (E, F) each tap's weight: area share × lit.
    light
        (E, 3) unit directions to the light.
    grey_intensity
        (E, 3) e_c times the Rec. 601 weight of channel c.
    view
        (3,) unit direction to the camera.
    tap_area
        (E, F) each tap's area share without the mask, for a model with indirect light.
    shaded
        (E·F, 3) ``shade_rows`` of the taps (``tap_rows``), where the caller rendered them (None:
        rendered here).

    Returns
    -------
    Tensor
        (E,) grey irradiance.
    """
    e, f = tap_pixel.shape
    if shaded is None:
        shaded = shade_rows(model, normal, maps, *tap_rows(tap_pixel, light), view)
    grey = torch.sum(torch.sum(shaded.reshape(e, f, 3) * grey_intensity[:, None, :], dim=-1) * tap_weight, dim=-1)
    if not model.indirect:
        return grey
    flat = tap_pixel.reshape(-1)
    indirect = model.indirect_light({name: maps[name][flat] for name in (model.diffuse, INDIRECT.name) if name is not None})
    assert indirect is not None and tap_area is not None, "a model with indirect light needs the taps' areas"
    return grey + torch.sum(torch.sum(indirect.reshape(e, f, 3) * grey_intensity[:, None, :], dim=-1) * tap_area, dim=-1)


def tap_rows(tap_pixel: Tensor, light: Tensor) -> tuple[Tensor, Tensor]:
    """The rows ``shade_rows`` renders for ``superpixel_grey``: (E·F,) the taps' pixels, (E·F, 3) each
    tap's super pixel's light (``tap_pixel`` (E, F), ``light`` (E, 3))."""
    e, f = tap_pixel.shape
    return tap_pixel.reshape(-1), light[:, None, :].expand(e, f, 3).reshape(-1, 3)
