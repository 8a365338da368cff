"""The training losses of DualResPS (eq. 24–26).

- Frames (eq. 24): mean L1 between rendered and measured frame values. A value the sensor clipped
  (``saturated``) only says the truth was at least 1: it is penalised only while the rendering stays
  below 1, so highlights that clip do not pull the fit down.
- Events (eq. 25): weighted squared residual of the log ratio of the rendered grey irradiance at an
  event and at its reference time against the fired contrast: ln((Ĩ_k + ε)/(Ĩ_ref + ε)) − ln α − p·C;
  with a Huber δ (``robust_square``) a residual beyond δ counts linearly, so the pairs the model cannot
  explain — noise events, a threshold off its nominal value, light reflected from other parts of the
  object — pull the fit with a bounded force instead of one that grows with their residual.
- Total variation (eq. 26, the warm-up term of LL22a): mean L1 difference of neighbouring pixels.
"""

from __future__ import annotations

import torch
from torch import Tensor

from pstoolkit_dualres.gather import gather_sum


def frame_loss(predicted: Tensor, measured: Tensor, saturated: Tensor) -> Tensor:
    """Mean |Ã − A| over (values, 3); ``saturated`` (values,) bool marks clipped measurements."""
    residual = torch.where(saturated[:, None], torch.relu(1.0 - predicted), (predicted - measured).abs())
    return residual.mean()


def robust_square(residual: Tensor, huber: float) -> Tensor:
    """r² within ``huber`` δ (all of it for δ ≤ 0), 2δ|r| − δ² beyond: Huber's loss times two, so that
    within δ it is the plain square of eq. 25."""
    if huber <= 0:
        return residual * residual
    clipped = residual.clamp(-huber, huber)
    return clipped * (2.0 * residual - clipped)


def event_loss(grey_t: Tensor, grey_ref: Tensor, target: Tensor, weight: Tensor, eps: float, huber: float = 0.0) -> Tensor:
    """Σ w·ρ_δ(ln((Ĩ_k + ε)/(Ĩ_ref + ε)) − target) / N_e with ``target`` = ln α + p·C per event pair and
    ρ_δ = ``robust_square`` (δ = ``huber``, log units)."""
    return torch.sum(weight * robust_square(log_residual(grey_t, grey_ref, target, eps), huber)) / max(int(target.numel()), 1)


def log_residual(grey_t: Tensor, grey_ref: Tensor, target: Tensor, eps: float) -> Tensor:
    """The event residual of eq. 25 per pair: ln((Ĩ_k + ε)/(Ĩ_ref + ε)) − target."""
    return torch.log(grey_t + eps) - torch.log(grey_ref + eps) - target


def tv_loss(values: Tensor, pairs: Tensor) -> Tensor:
    """Mean |v_a − v_b| over neighbour pairs (Q, 2) of rows of ``values`` (P, C)."""
    if pairs.numel() == 0:
        return values.sum() * 0.0
    difference = values.new_tensor([1.0, -1.0]).expand(pairs.shape[0], 2)
    return gather_sum(values, pairs, difference).abs().mean()
