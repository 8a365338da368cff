"""The irradiance scale's fit (``irradiance._fit_scale``) on a torch device: the midpoint-rule integrals
of exp(L) over each window's pieces of s, L interpolated between the knots as ``numpy.interp`` does
(the same interval and expression), summed per piece, and the per-pixel least squares by a batched
pseudo-inverse at numpy's default cutoff. Equal to the host's to rounding (the order of the device's
sums, its exp). At 1024² on the host it took 5 s, one core.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from pstoolkit import US_PER_S

if TYPE_CHECKING:
    from pstoolkit_dualres.irradiance import Irradiance

# Super pixels per block on the device: a block's (pixels, samples) float64 arrays take about 50 MB.
DEVICE_SCALE_BLOCK = 1 << 16
# numpy.linalg.pinv's default cutoff of small singular values, relative to the largest.
PINV_RCOND = 1e-15


def interp(x: Tensor, xp: Tensor, fp: Tensor) -> Tensor:
    """``numpy.interp(x, xp, fp)`` for increasing ``xp`` (K ≥ 2,): fp[0] before xp[0], fp[-1] after
    xp[-1], else slope·(x − xp[j]) + fp[j] on the interval xp[j] ≤ x < xp[j + 1]."""
    j = torch.clamp(torch.searchsorted(xp, x, right=True) - 1, 0, xp.numel() - 2)
    slope = (fp[j + 1] - fp[j]) / (xp[j + 1] - xp[j])
    inside = slope * (x - xp[j]) + fp[j]
    return torch.where(x < xp[0], fp[0], torch.where(x >= xp[-1], fp[-1], inside))


def fit_scale_there(irradiance: Irradiance, frame_values: np.ndarray, samples: int, device: str | torch.device) -> np.ndarray:
    """``irradiance._fit_scale`` on ``device``, ``samples`` midpoint-rule samples a window
    (``irradiance.SCALE_SAMPLES``): s per (pixel, piece), (n_pixels, pieces) float64."""
    dtype = torch.float64
    n_pixels, n_windows = frame_values.shape
    bounds, period = irradiance.bounds_us, irradiance.period_us
    keys = torch.as_tensor(irradiance.knot_key, dtype=dtype, device=device)
    logs = torch.as_tensor(irradiance.knot_log, dtype=dtype, device=device)
    changes = torch.as_tensor(irradiance.change_us, dtype=dtype, device=device)
    pieces = changes.shape[1]
    count = torch.isfinite(changes).sum(dim=1)
    integrals = torch.zeros((n_pixels, n_windows, pieces), dtype=dtype, device=device)
    for j in range(n_windows):
        width = bounds[j + 1] - bounds[j]
        phase_np = bounds[j] + (np.arange(samples) + 0.5) * width / samples
        phase = torch.as_tensor(phase_np, device=device)
        wrapped = torch.as_tensor(np.mod(phase_np, period), device=device)
        dt_s = width / samples / US_PER_S
        for start in range(0, n_pixels, DEVICE_SCALE_BLOCK):
            pix = torch.arange(start, min(start + DEVICE_SCALE_BLOCK, n_pixels), device=device)
            key = pix.to(dtype)[:, None] * 3.0 * period + period + wrapped[None, :]
            unscaled = torch.exp(interp(key, keys, logs)) * dt_s
            # ``Irradiance.piece``: change points passed, cyclically, where the pixel has any
            passed = (changes[pix][:, None, :] <= phase[None, :, None]).sum(dim=2)
            k = count[pix][:, None]
            piece = torch.where(k > 0, torch.remainder(passed - 1, torch.clamp(k, min=1)), 0)
            slot = (torch.arange(pix.numel(), device=device)[:, None] * pieces + piece).reshape(-1)
            summed = torch.zeros(pix.numel() * pieces, dtype=dtype, device=device).index_add_(0, slot, unscaled.reshape(-1))
            integrals[pix, j] = summed.reshape(-1, pieces)
    values = torch.as_tensor(frame_values, dtype=dtype, device=device)
    scale = torch.einsum("pmj,pj->pm", torch.linalg.pinv(integrals, rtol=PINV_RCOND), values)
    # one constant s where the pieces' fit is not physical
    total = integrals.sum(dim=2)
    energy = torch.einsum("pj,pj->p", total, total)
    constant = torch.einsum("pj,pj->p", total, values) / torch.where(energy > 0, energy, 1.0)
    bad = ~torch.all(torch.isfinite(scale) & (scale >= 0), dim=1)
    scale[bad] = constant[bad, None]
    return scale.cpu().numpy()
