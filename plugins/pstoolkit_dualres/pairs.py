"""The event samples of DualResPS eq. 25: pairs of times at one super pixel whose log irradiance
differs by a known amount, with a confidence weight.

The capture's refractory rule (``pstoolkit.events.rule``) decides the pairs, so that the relation is
exact rather than compensated after the fact (the paper's α = 1): with "reset-at-end" each event k
is paired with the reference level taken at t_{k−1} + R, ln I(t_k) − ln I(t_{k−1} + R) = p_k·C^{p_k};
with "rate-limited" consecutive events that fired at a crossing are paired with the sum of the
thresholds of the events between them (``pstoolkit.events.rule.exact_pairs``). Pairs longer than
``max_pair_share`` of the period are dropped (a pixel that was dark that long carries no shading).
The weight is min(1, Î/(dark_level·Î₅₀)) with Î the approximated irradiance at the pair's darker end
and Î₅₀ its median over all pairs (``DARK_REFERENCE_PERCENTILE``): events in dark regions are sensitive
to noise and to light the model does not have (main §3.3) — inter-reflection in a concavity that sits
in cast shadow most of the turn, ambient light. The median is the scene's typical lit level whatever
its highlights (a 99th percentile is a metal's highlight, against which its whole diffuse-free tail is
dark); ``benchmarks/NOTES.md`` has the sweep.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import psfmt
from pstoolkit.events.rule import exact_pairs
from pstoolkit_dualres.irradiance import Irradiance

DARK_REFERENCE_PERCENTILE = 50.0
"""The percentile of the pairs' darker-end irradiance that ``dark_level`` is a share of."""


@dataclass
class EventSamples:
    """Pairs at event pixels ``pixel`` (E,): the log irradiance at ``t_us`` (E,) float64 exceeds the
    one at ``t_ref_us`` (E,) float64 by ``target`` (E,) log units, ``rise`` − ``fall``: the nominal
    thresholds of its positive and of its negative events, (E,) float64 each; ``weight`` (E,) float32
    ≥ 0."""

    pixel: np.ndarray
    t_ref_us: np.ndarray
    t_us: np.ndarray
    target: np.ndarray
    weight: np.ndarray
    rise: np.ndarray
    fall: np.ndarray


def event_samples(
    events: psfmt.EventArray,
    width: int,
    irradiance: Irradiance,
    *,
    rule: str,
    refractory_us: float,
    contrast_pos: float,
    contrast_neg: float,
    t0_us: float,
    period_us: float,
    confidence: str,
    dark_level: float,
    max_pair_share: float,
) -> EventSamples:
    """The event samples of eq. 25 of a time-sorted stream (see the module docstring).

    Parameters
    ----------
    events
        The event stream, sorted by time.
    width
        The sensor's width in pixels (pixel index y·width + x).
    irradiance
        Î of the super pixels over the period starting at ``t0_us``, for the confidence.
    rule
        The refractory rule, one of ``pstoolkit.events.rule.REFRACTORY_RULES``.
    refractory_us
        The refractory period R, µs.
    contrast_pos, contrast_neg
        Thresholds C⁺ and C⁻, log units.
    t0_us, period_us
        Start of the irradiance's period and the light period, µs.
    confidence
        "linear": the weight min(1, Î/(dark_level·Î₅₀)); any other value (``preprocess``'s "none"):
        weight 1.
    dark_level
        Share of Î₅₀ below which a pair's weight falls linearly.
    max_pair_share
        Longest pair kept, as a share of the period.

    Returns
    -------
    EventSamples
        The pairs kept, with their log change and weight.

    Raises
    ------
    UserError
        An unknown rule.
    """
    pairs = exact_pairs(events, width, rule, refractory_us, contrast_pos, contrast_neg)
    t = pairs.t_us.astype(np.float64)
    keep = t - pairs.t_ref_us <= max_pair_share * period_us
    pixel, t_ref, t, target = pairs.pixel[keep], pairs.t_ref_us[keep], t[keep], pairs.delta_log[keep]
    rise, fall = pairs.n_pos[keep] * float(contrast_pos), pairs.n_neg[keep] * float(contrast_neg)
    if confidence == "linear":
        darker = np.minimum(irradiance.value(pixel, t_ref - t0_us), irradiance.value(pixel, t - t0_us))
        bright = float(np.percentile(darker, DARK_REFERENCE_PERCENTILE)) if darker.size else 0.0
        level = dark_level * bright
        weight = np.clip(darker / level, 0.0, 1.0) if level > 0 else np.ones(len(t))
    else:
        weight = np.ones(len(t))
    return EventSamples(pixel=pixel, t_ref_us=t_ref, t_us=t, target=target, weight=weight.astype(np.float32), rise=rise, fall=fall)
