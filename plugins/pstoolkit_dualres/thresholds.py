"""Each event pixel's own contrast thresholds, estimated with the fit (``thresholds``, ``threshold_sigma``).

A real event pixel's thresholds are not the nominal C⁺ and C⁻: the comparators of a sensor spread
around them (σ ≈ 0.03 log units on DVS pixels, ``docs/sensors.md``), so a pixel whose C⁺ is 13 % high
reports every rise 13 % steeper than it was. The event term, fitting the nominal steps, then tilts the
pixel's normal until its rendered log profile takes that amplitude, against the frames. With the
thresholds as unknowns the events keep what the spread does not touch — when the light crosses each
level, the shape of the profile — and the frames, which no threshold scales, fix the amplitude.

Every ``REFIT_EVERY`` epochs the solver takes the current fit's log change across each pair (the
rendered one the event term compares) and solves, per event pixel, for gains g⁺ and g⁻ on its nominal
thresholds that best explain its pairs' changes — rise·g⁺ − fall·g⁻, rise and fall the nominal
thresholds of the pair's positive and negative events — in least squares with the Gaussian prior of
the sensor's spread σ; pairs whose residual exceeds ``CLIP`` robust standard deviations (noise events,
light the model lacks) do not count. Each refit starts from the model the last one left, so the gains
and the normals settle together: one estimate from a fit made with the nominal thresholds recovers
under half of the spread, because that fit has already bent towards it.

By default only the balance of the two is estimated — g⁺ = e^d, g⁻ = e^−d, d ~ N(0, (σ/C)²/2), half
the spread's variance. Light the model lacks imitates a common scale: the walls of a concavity reflect
light into it, which flattens the log profile of a whole region, rises and falls alike as both pass
the same levels over a turn. Estimating the common scale too (``common``) took that flattening for
thresholds on the walls of path-traced hollows (the gains' error against the sensor's drawn thresholds
above the spread itself); kept relative to the median of its ``NEIGHBOURHOOD`` × ``NEIGHBOURHOOD``
neighbours' — the comparators spread independently from pixel to pixel, the flattening does not — it
still costs path-traced captures in their 90th percentile what it gains on the simulator's
(``docs/dualres-tuning.md``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import median_filter
from torch import nn

from pstoolkit_dualres.consistency import pair_residuals
from pstoolkit_dualres.problem import Problem
from pstoolkit_dualres.reflectance import FitModel

# What ``fit_thresholds`` may estimate: nothing, the balance of C⁺ and C⁻, or also their common scale.
THRESHOLD_FITS = ("nominal", "balance", "both")
# Epochs between refits: often enough that the gains follow the normals within a stage.
REFIT_EVERY = 10
# Robust standard deviations (1.4826 × the median absolute residual) beyond which a pair does not count.
CLIP = 3.0
# Event pixels per side of the neighbourhood whose median gain each pixel's is taken relative to.
NEIGHBOURHOOD = 3
# The gains are kept within [1 / GAIN_BOUND, GAIN_BOUND]: beyond, a pixel's pairs say something other
# than a threshold's spread.
GAIN_BOUND = 2.0


@dataclass(frozen=True)
class ThresholdGains:
    """``gain_pos``, ``gain_neg`` (He·We,) the factors on the nominal C⁺ and C⁻ of each event pixel,
    ``residual_scale`` the robust standard deviation of the pairs' log residuals they were fitted at."""

    gain_pos: np.ndarray
    gain_neg: np.ndarray
    residual_scale: float

    def record(self) -> dict[str, float]:
        """For a run's diagnostics: the spread (5th and 95th percentiles) of the gains that moved."""
        moved = (self.gain_pos != 1.0) | (self.gain_neg != 1.0)
        pos, neg = (np.percentile(g[moved], [5.0, 95.0]) if moved.any() else (1.0, 1.0) for g in (self.gain_pos, self.gain_neg))
        return {"threshold_residual": self.residual_scale, "gain_pos_p5": float(pos[0]), "gain_pos_p95": float(pos[1]),
                "gain_neg_p5": float(neg[0]), "gain_neg_p95": float(neg[1])}


def fit_thresholds(problem: Problem, field: nn.Module, model: FitModel, event_shape: tuple[int, int], sigma: float,
                   contrast_pos: float, contrast_neg: float, *, common: bool = False) -> ThresholdGains:
    """The gains on each event pixel's nominal thresholds under the current fit (module docstring).

    Parameters
    ----------
    problem, field, model
        The fit; its event pairs' ``source`` holds each pair's ``rise`` and ``fall``.
    event_shape
        (He, We), the event grid the gains are compared across.
    sigma
        Spread of the pixels' thresholds around the nominal ones, log units (> 0).
    contrast_pos, contrast_neg
        The nominal C⁺ and C⁻, log units: the prior's relative spreads are σ/C⁺ and σ/C⁻.
    common
        Also the common scale of a pixel's two thresholds, relative to its neighbourhood's
        (``NEIGHBOURHOOD``); without, only their balance: g⁺ = e^d, g⁻ = e^−d.

    Returns
    -------
    ThresholdGains
        Per event pixel, within [1/GAIN_BOUND, GAIN_BOUND]; 1 for a pixel without usable pairs.
    """
    n_event_pixels = event_shape[0] * event_shape[1]
    events = problem.events
    usable = events.usable
    chosen = usable.cpu().numpy()
    residual = pair_residuals(problem, field, model, usable)
    scale = 1.4826 * float(np.median(np.abs(residual))) if residual.size else 0.0
    if scale <= 0.0:
        # nothing to fit, or a fit with nothing left to explain
        return ThresholdGains(np.ones(n_event_pixels), np.ones(n_event_pixels), scale)
    # the rendered change: what the residual adds to the target it was taken against
    change = residual + events.target[usable].double().cpu().numpy()
    src = events.source
    pixel, rise, fall = src["pixel"][chosen], src["rise"][chosen], src["fall"][chosen]
    weight = src["weight"][chosen] * (np.abs(residual) <= CLIP * scale)

    def total(values: np.ndarray) -> np.ndarray:
        return np.bincount(pixel, weights=weight * values, minlength=n_event_pixels)

    bound = np.log(GAIN_BOUND)
    if not common:
        # change ≈ rise·(1 + d) − fall·(1 − d): least squares in d with the prior of (ln g⁺ − ln g⁻)/2,
        # whose variance is half of (σ/C)², C the mean threshold
        mean_contrast = 0.5 * (contrast_pos + contrast_neg)
        prior = 2.0 * (scale * mean_contrast / sigma) ** 2
        spread = rise + fall
        d = np.clip(total(spread * (change - rise + fall)) / (total(spread * spread) + prior), -bound, bound)
        return ThresholdGains(np.exp(d), np.exp(-d), scale)
    # a gain off by δ moves a one-threshold pair by C·δ: the prior N(1, (σ/C)²) weighs (scale·C/σ)²
    prior_pos, prior_neg = (scale * contrast_pos / sigma) ** 2, (scale * contrast_neg / sigma) ** 2
    # normal equations of Σ w (change − rise·g⁺ + fall·g⁻)² + λ⁺(g⁺ − 1)² + λ⁻(g⁻ − 1)², per pixel
    a, b, c = total(rise * rise) + prior_pos, -total(rise * fall), total(fall * fall) + prior_neg
    u, v = total(rise * change) + prior_pos, prior_neg - total(fall * change)
    det = a * c - b * b
    gains = []
    for raw in ((c * u - b * v) / det, (a * v - b * u) / det):
        log_gain = np.log(np.clip(raw, 1.0 / GAIN_BOUND, GAIN_BOUND)).reshape(event_shape)
        gains.append(np.exp(log_gain - median_filter(log_gain, size=NEIGHBOURHOOD, mode="nearest")).ravel())
    return ThresholdGains(gains[0], gains[1], scale)
