"""Asynchronous importance sampling of the exposure integrals (DualResPS eq. 21 and 23).

Each super pixel's period is cut at its events and at the exposure window bounds. A segment of Δt
seconds over which the approximated irradiance Î changes by ΔÎ gets

    N = ⌈round(σ·√(ΔÎ·Δt)) − 1⌉₊      extra samples (eq. 23),

so N + 1 equal sub-intervals, each sampled at its midpoint with weight dt = its length: the sum
Σ I(t)·dt over a window's samples is the midpoint rule for the frame integral, and samples crowd
where the irradiance changes fast. A segment is also cut so no sub-interval is longer than
``max_step_us``, which keeps the light's own sweep resolved where events are sparse. The samples are
fixed once, here; a cast-shadow mask weighs them later (``problem``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pstoolkit import US_PER_S
from pstoolkit_dualres.irradiance import Irradiance

# Fraction of a segment kept away from its ends when reading Î there: the scale jumps at segment
# ends, and the change across the segment is what eq. 23 needs.
EDGE = 1e-6


@dataclass
class Samples:
    """Sample times of the super pixels: ``pixel`` (M,) event flat index, ``window`` (M,) exposure
    window, ``phase_us`` (M,) float64 phase in [0, period), ``dt_s`` (M,) weight in seconds; grouped
    by pixel, in time order within a pixel."""

    pixel: np.ndarray
    window: np.ndarray
    phase_us: np.ndarray
    dt_s: np.ndarray


def segment_counts(delta_irradiance: np.ndarray, dt_s: np.ndarray, sigma: float) -> np.ndarray:
    """Eq. 23: extra samples ⌈round(σ·√(ΔÎ·Δt)) − 1⌉₊ per segment (ΔÎ per second, Δt seconds)."""
    return np.maximum(np.rint(sigma * np.sqrt(np.abs(delta_irradiance) * dt_s)) - 1.0, 0.0).astype(np.int64)


def importance_samples(
    irradiance: Irradiance,
    event_pixel: np.ndarray,
    event_phase_us: np.ndarray,
    *,
    n_pixels: int,
    sigma: float,
    max_step_us: float,
) -> Samples:
    """Samples of every super pixel over the exposure windows of ``irradiance`` (see the module
    docstring): each segment between events and window bounds gets N + 1 midpoint samples (eq. 23).

    Parameters
    ----------
    irradiance
        Î of the super pixels over one period, with the windows' bounds ``bounds_us``.
    event_pixel, event_phase_us
        (E,) flat event pixels and phases, µs in [0, period), of the events of the period the
        irradiance was built from.
    n_pixels
        Number of super pixels (event pixels).
    sigma
        σ of eq. 23: the sampling density.
    max_step_us
        Longest sub-interval, µs.

    Returns
    -------
    Samples
        Grouped by pixel, in time order within a pixel; within a window the weights ``dt_s`` sum to its
        length in seconds.
    """
    period = irradiance.period_us
    stride = 2.0 * period
    bounds = irradiance.bounds_us
    every = np.arange(n_pixels, dtype=np.float64)
    cuts = [event_pixel * stride + event_phase_us, (every[:, None] * stride + bounds[None, :]).ravel()]
    key = np.unique(np.concatenate(cuts))
    pixel_of = np.floor(key / stride)
    inside = (key - pixel_of * stride >= bounds[0]) & (key - pixel_of * stride <= bounds[-1])
    key, pixel_of = key[inside], pixel_of[inside]
    same = pixel_of[1:] == pixel_of[:-1]
    lo, hi, pix = key[:-1][same], key[1:][same], pixel_of[:-1][same].astype(np.int64)
    length = hi - lo
    keep = length > 0
    lo, hi, pix, length = lo[keep], hi[keep], pix[keep], length[keep]
    base = pix * stride
    start_value = irradiance.value(pix, lo - base + EDGE * length)
    end_value = irradiance.value(pix, hi - base - EDGE * length)
    extra = segment_counts(end_value - start_value, length / US_PER_S, sigma)
    parts = np.maximum(extra + 1, np.ceil(length / max_step_us).astype(np.int64))
    segment = np.repeat(np.arange(len(lo)), parts)
    within = np.arange(segment.size) - np.repeat(np.cumsum(parts) - parts, parts)
    sub = length[segment] / parts[segment]
    phase = lo[segment] - base[segment] + (within + 0.5) * sub
    return Samples(pixel=pix[segment], window=irradiance.window(phase), phase_us=phase, dt_s=sub / US_PER_S)
