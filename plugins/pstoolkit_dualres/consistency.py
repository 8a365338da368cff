"""Which event pixels the fitted model explains, and how much their events may pull (``event_gate``).

The event term assumes that every change a pixel saw came from the direct light on its own normal.
Where something else changes the light — the walls of a hollow reflecting the moving light into it
while the direct light is cast off, a hot or leaking pixel, a threshold far from its nominal value —
its pairs have residuals no normal can remove, and with the term's weight they drag the pixel's
normal wherever they point, through a fit the frames alone had right. Between stages the solver
therefore measures each event pixel's robust residual scale (the root of the median squared log
residual of its pairs under the current fit) against the capture's typical one (the median of those
scales) and keeps its pairs' full weight up to ``kappa`` times the typical scale — and at least up to
half the smaller contrast threshold, the residual an event's own quantisation leaves, so that a fit
that explains nearly everything does not gate its rim for residuals no sensor resolves — beyond which
the weight falls as (bound / scale)²: the pixel-level counterpart of Cauchy-style reweighting.
The frame pixels under a pixel whose weight fell below one half restart from the closed form of
their frames, as the pixels a new shadow mask covers do.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from pstoolkit.events.rule import LOG_EPS
from pstoolkit_dualres.losses import log_residual, pair_grey
from pstoolkit_dualres.problem import Problem
from pstoolkit_dualres.reflectance import FitModel

# Pairs whose residuals are computed at once (bounds the (pairs, taps) intermediates).
CHUNK_PAIRS = 1 << 16
# Fewer pairs than this leave a pixel's scale unmeasured (its weight stays).
MIN_PAIRS = 4


@dataclass
class Gate:
    """``weight`` (He·We,) float in (0, 1] per event pixel, ``scale`` (He·We,) its residual scale
    (NaN where unmeasured), ``typical`` the capture's median scale and ``restart`` (He·We,) bool the
    pixels whose frame pixels restart from the closed form."""

    weight: np.ndarray
    scale: np.ndarray
    typical: float
    restart: np.ndarray

    def record(self) -> dict[str, float]:
        """For a run's diagnostics: the typical scale and the shares of gated and restarted pixels."""
        measured = ~np.isnan(self.scale)
        return {"typical_residual": self.typical, "gated_share": float(np.mean(self.weight[measured] < 1.0)) if measured.any() else 0.0,
                "restarted_share": float(np.mean(self.restart[measured])) if measured.any() else 0.0}


@torch.no_grad()
def pair_residuals(problem: Problem, field: nn.Module, model: FitModel, pairs: torch.Tensor) -> np.ndarray:
    """(len(pairs),) float64 log residual of each event ``pairs`` (indices into ``problem.events``)
    under the current fit: the event term's residual, before its weight and robust loss."""
    normal, pixel_raw, smooth_raw = field()
    maps = model.maps(pixel_raw, smooth_raw)
    events, view = problem.events, problem.geometry.view
    out = np.empty(pairs.numel(), dtype=np.float64)
    for start in range(0, pairs.numel(), CHUNK_PAIRS):
        e = pairs[start : start + CHUNK_PAIRS]
        now, ref = pair_grey(model, normal, maps, events.taps[e], events, e, view)
        out[start : start + e.numel()] = log_residual(now, ref, events.target[e], LOG_EPS).double().cpu().numpy()
    return out


def event_gate(problem: Problem, field: nn.Module, model: FitModel, n_event_pixels: int, kappa: float,
               floor: float) -> Gate:
    """The weight of each event pixel's pairs (module docstring) under the current fit: 1 up to the
    bound max(``kappa`` × the typical residual scale, ``floor``) (log units), (bound / scale)² beyond;
    ``restart`` where it fell below one half. Pixels with fewer than MIN_PAIRS usable pairs keep
    weight 1."""
    events = problem.events
    usable = events.usable
    pixel = events.pixel[usable.cpu().numpy()]
    squared = pair_residuals(problem, field, model, usable) ** 2
    # sorted by pixel, then by value: each pixel's median is the middle of its run
    order = np.lexsort((squared, pixel))
    pixel, squared = pixel[order], squared[order]
    first = np.searchsorted(pixel, np.arange(n_event_pixels))
    count = np.searchsorted(pixel, np.arange(n_event_pixels), side="right") - first
    scale = np.full(n_event_pixels, np.nan)
    enough = np.flatnonzero(count >= MIN_PAIRS)
    low, high = first[enough] + (count[enough] - 1) // 2, first[enough] + count[enough] // 2
    scale[enough] = np.sqrt(0.5 * (squared[low] + squared[high]))
    measured = ~np.isnan(scale)
    typical = float(np.median(scale[measured])) if measured.any() else 0.0
    weight = np.ones(n_event_pixels)
    bound = max(kappa * typical, floor)
    if bound > 0:
        over = measured & (scale > bound)
        weight[over] = (bound / scale[over]) ** 2
    return Gate(weight=weight, scale=scale, typical=typical, restart=weight < 0.5)
