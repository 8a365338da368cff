"""The closed form's fixed point (``fixed_point.fixed_point``) on a torch device: the same iteration
of the attached-shadow clamp, each window's per-pixel equivalent lights one (P, S)·(S, 9) product of
the samples' visibility and clamp against their weighted light directions
(``pstoolkit.optics.equivalent.equivalent_lights`` for a directional light), the 3×3 systems solved
in a batch. In float64 like the host's, equal to it to rounding: a pixel on the threshold of an
effective light or of the 0.01° that settles it may decide the other way. At 1024² on the host it
took 10 s a solve; the lights stay on the device for the albedo.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from pstoolkit import GREY_WEIGHTS, US_PER_S, LightModel
from pstoolkit.optics.equivalent import sample_times
from pstoolkit_dualres.fixed_point import EFFECTIVE_SHARE, MOVED_COS, FixedPoint

LINALG_BATCH = 16384


@dataclass
class DeviceLights:
    """The per-pixel equivalent lights ``lights`` (J, P, 3, 3) float64 of a fixed point solved on
    their device (``fixed_point.HostLights`` on the host)."""

    lights: Tensor

    def grey_at(self, index: np.ndarray) -> np.ndarray:
        """(J, n, 3) the grey lights of the pixels ``index`` (bool (P,) or positions)."""
        chosen = torch.as_tensor(np.flatnonzero(index) if index.dtype == bool else index, device=self.lights.device)
        return _grey(self.lights[:, chosen]).cpu().numpy()

    def albedo(self, rgb: np.ndarray, effective: np.ndarray, normal: np.ndarray) -> np.ndarray:
        """(P, 3) ``fixed_point._albedo`` of the windows' values ``rgb`` (J, P, 3) with these lights."""
        device = self.lights.device
        shading = torch.einsum("jpcx,px->jpc", self.lights, torch.as_tensor(normal, device=device))
        shading = shading * torch.as_tensor(effective, device=device)[..., None]
        num = torch.einsum("jpc,jpc->pc", torch.as_tensor(rgb, dtype=torch.float64, device=device), shading)
        den = torch.einsum("jpc,jpc->pc", shading, shading)
        return torch.where(den > 0, num / torch.where(den > 0, den, 1.0), 0.0).cpu().numpy()


def _grey(lights: Tensor) -> Tensor:
    return torch.einsum("c,...cx->...x", torch.as_tensor(GREY_WEIGHTS, dtype=lights.dtype, device=lights.device), lights)


def _unit(vectors: Tensor) -> Tensor:
    norm = torch.linalg.vector_norm(vectors, dim=-1, keepdim=True)
    return torch.where(norm > 0, vectors / torch.where(norm > 0, norm, 1.0), 0.0)


def _in_batches(op: Callable[..., Tensor], *tensors: Tensor) -> Tensor:
    """``op`` of a batch of small systems (``tensors``, the same length B), ``LINALG_BATCH`` systems a
    call: on CUDA one batched ``eigvalsh`` of more (65 536 at 256²) fails inside cuSOLVER (an internal
    error, or a workspace of terabytes at 5 M), and a system's answer does not depend on its batch."""
    return torch.cat([op(*parts) for parts in zip(*(torch.split(t, LINALG_BATCH) for t in tensors))])


def _solve(grey_lights: Tensor, grey: Tensor, usable: Tensor) -> Tensor:
    """``fixed_point._solve``: b = ρ·n per pixel, least squares over the usable windows, zero where
    fewer than three or a singular system."""
    w = usable.to(grey.dtype)
    lhs = torch.einsum("jp,jpx,jpy->pxy", w, grey_lights, grey_lights)
    rhs = torch.einsum("jp,jpx,jp->px", w, grey_lights, grey)
    eig = _in_batches(torch.linalg.eigvalsh, lhs)
    ok = (usable.sum(dim=0) >= 3) & (eig[:, 0] > 1e-9 * torch.clamp(eig[:, 2], min=1e-300))
    b = torch.zeros_like(rhs)
    b[ok] = _in_batches(torch.linalg.solve, lhs[ok], rhs[ok])
    return b


def device_fixed_point(light: LightModel, windows_us: np.ndarray, grey: np.ndarray, masks: list[np.ndarray | Tensor] | None, *,
                       iterations: int, n_samples: int, device: str | torch.device) -> FixedPoint:
    """``fixed_point.fixed_point`` on ``device`` (module docstring); the same arguments, and a
    ``FixedPoint`` whose lights stay there (``DeviceLights``)."""
    dtype = torch.float64
    n_windows, n_pixels = grey.shape
    weights, visible = [], []
    for j, (t0, t1) in enumerate(windows_us):
        direction, intensity = light.evaluate(sample_times(t0, t1, n_samples))
        dt_s = (float(t1) - float(t0)) / n_samples / US_PER_S
        # (S, 9): e_c(t)·l(t) for every sample, as ``equivalent_lights`` weighs them
        weights.append((torch.as_tensor((intensity[:, :, None] * direction[:, None, :]).reshape(n_samples, 9) * dt_s,
                                        device=device), torch.as_tensor(direction, device=device)))
        visible.append(None if masks is None else torch.as_tensor(masks[j], device=device))
    free = torch.stack([_grey(w.sum(dim=0).reshape(3, 3)) for w, _ in weights])
    threshold = EFFECTIVE_SHARE * torch.linalg.vector_norm(free, dim=-1)[:, None]  # (J, 1)
    values = torch.as_tensor(grey, dtype=dtype, device=device)
    normal = torch.zeros((n_pixels, 3), dtype=dtype, device=device)
    normal[:, 2] = 1.0
    lights = torch.empty((n_windows, n_pixels, 3, 3), dtype=dtype, device=device)
    effective = torch.zeros((n_windows, n_pixels), dtype=torch.bool, device=device)
    solved = torch.zeros(n_pixels, dtype=torch.bool, device=device)
    active = torch.arange(n_pixels, device=device)
    done = 0
    for done in range(1, max(iterations, 1) + 1):  # noqa: B007 -- the count after the loop is the record
        facing = normal[active]
        for j, (weight, direction) in enumerate(weights):
            lit = direction @ facing.T > 0  # (S, A): the attached-shadow clamp
            if visible[j] is not None:
                lit &= visible[j][:, active]
            lights[j, active] = (lit.T.to(dtype) @ weight).reshape(-1, 3, 3)
        grey_lights = _grey(lights[:, active])
        effective[:, active] = torch.linalg.vector_norm(grey_lights, dim=-1) >= threshold
        updated = _unit(_solve(grey_lights, values[:, active], effective[:, active]))
        moved = torch.any(updated != 0, dim=1)
        solved[active] = moved
        change = torch.sum(updated * facing, dim=1)
        normal[active[moved]] = updated[moved]
        active = active[moved & (change < MOVED_COS)]
        # the one read of the device per iteration
        if active.numel() == 0:
            break
    return FixedPoint(normal.cpu().numpy(), effective.cpu().numpy(), solved.cpu().numpy(), done, DeviceLights(lights))
