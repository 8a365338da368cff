"""Approximated irradiance at the super pixels over one period (supplement eq. 1).

Î(t) = s(t) · exp(L(t)) · (1 − m_c(t)), where L is the cumulative log change of the events,

    L_k = Σ_{κ ≤ k} (log α_κ + p_κ C^{p_κ}),

α_κ compensates the change the sensor missed in its refractory period R after event κ−1 (it is
blind then and resets its reference at the end, ``pstoolkit.events.rule``): assuming the log changed
at a constant rate over the interval, log α_κ = p_κ C · R / (Δt_κ − R), with the denominator floored
at R so at most one more threshold is credited. L is linear between events (that same constant
rate), and the residual drift over the period is removed linearly in time so L is periodic.

The scale s is piecewise constant with at most ``MAX_PIECES`` values per period. It changes value
only where the interval profile |f| (eq. 20) reaches ``threshold_per_s`` — an abrupt change where
the refractory compensation may have failed: at the end of each run of such events (the burst of
one edge), the (up to) three with the largest |f| of the super pixel; k change points cut the
cyclic period into k pieces (none or one: s is constant). ``approximate`` without the profile puts
the changes at the exposure window bounds instead (one value per window). The values are the
least-squares solution of the frames' constraint
Σ_m s_m ∫_{window j ∩ piece m} exp(L) dt = A_j: three windows, at most three unknowns, so the
frame values (the area mean of the super pixel's frame pixels, in saturation units) fix the
absolute level and the jumps the events cannot, and the system is never underdetermined. A fit
that gives a piece a negative or non-finite value falls back to one constant s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pstoolkit import US_PER_S
from pstoolkit._shared import devices
from pstoolkit_dualres.irradiance_device import fit_scale_there

# Midpoint-rule samples per exposure window when fitting the scale s.
SCALE_SAMPLES = 96
# Most distinct values of s per period (supplement §2.2).
MAX_PIECES = 3
# Super pixels per block when fitting the scale, so a block's (pixels, samples) arrays stay small.
SCALE_BLOCK = 4096


def refractory_log_alpha(p: np.ndarray, contrast: np.ndarray, interval_us: np.ndarray, refractory_us: float) -> np.ndarray:
    """log α: the log change credited to the refractory period before each event (constant-rate
    assumption; ``interval_us`` is the time since the previous event of the pixel)."""
    if refractory_us <= 0:
        return np.zeros(len(p))
    seen = np.maximum(np.asarray(interval_us, dtype=np.float64) - refractory_us, refractory_us)
    return p * contrast * refractory_us / seen


@dataclass
class Irradiance:
    """Î per super pixel as knots of L (keys ``pixel·3T + T + phase``, phases in [−T, 2T) so every
    pixel's knots cover its whole period), the phases where s changes ``change_us`` (n_pixels, M)
    (sorted, NaN-padded), the scale ``scale`` (n_pixels, M) per piece (saturation units per second)
    and the exposure windows ``bounds_us`` (J+1,) phases."""

    knot_key: np.ndarray
    knot_log: np.ndarray
    change_us: np.ndarray
    scale: np.ndarray
    bounds_us: np.ndarray
    period_us: float

    def log_level(self, pixel: np.ndarray, phase_us: np.ndarray) -> np.ndarray:
        """L at event pixels ``pixel`` and phases ``phase_us`` (reduced modulo the period)."""
        period = self.period_us
        key = np.asarray(pixel, dtype=np.float64) * 3.0 * period + period + np.mod(phase_us, period)
        return np.interp(key, self.knot_key, self.knot_log)

    def window(self, phase_us: np.ndarray) -> np.ndarray:
        """Index of the exposure window holding each phase (the last one past its end)."""
        phase = np.mod(np.asarray(phase_us, dtype=np.float64), self.period_us)
        return np.clip(np.searchsorted(self.bounds_us, phase, side="right") - 1, 0, len(self.bounds_us) - 2)

    def piece(self, pixel: np.ndarray, phase_us: np.ndarray) -> np.ndarray:
        """Index of the piece of s holding each phase: k change points cut the cycle into k pieces,
        piece m starting at the m-th one (the time before the first belongs to the last piece).
        ``pixel`` and ``phase_us`` broadcast against each other."""
        changes = self.change_us[np.asarray(pixel, dtype=np.int64)]
        phase = np.mod(np.asarray(phase_us, dtype=np.float64), self.period_us)
        k = np.sum(np.isfinite(changes), axis=-1)
        # one comparison per change point (at most a few): numpy sums a short last axis slowly
        passed = np.zeros(np.broadcast_shapes(k.shape, phase.shape), dtype=np.int64)
        for m in range(changes.shape[-1]):
            passed += changes[..., m] <= phase
        return np.where(k > 0, np.mod(passed - 1, np.maximum(k, 1)), 0)

    def value(self, pixel: np.ndarray, phase_us: np.ndarray) -> np.ndarray:
        """Î (saturation units per second) at event pixels and phases."""
        pixel = np.asarray(pixel, dtype=np.int64)
        level = np.exp(self.log_level(pixel, phase_us))
        return self.scale[pixel, self.piece(pixel, phase_us)] * level


def approximate(
    pixel: np.ndarray,
    t_us: np.ndarray,
    p: np.ndarray,
    first: np.ndarray,
    count: np.ndarray,
    *,
    n_pixels: int,
    period_us: float,
    contrast_pos: float,
    contrast_neg: float,
    refractory_us: float,
    bounds_us: np.ndarray,
    frame_values: np.ndarray,
    f: np.ndarray | None = None,
    threshold_per_s: float = np.inf,
    device: str = "cpu",
) -> Irradiance:
    """Î from one period's events and the super pixels' frame values (supplement eq. 1; see the module
    docstring).

    Parameters
    ----------
    pixel, t_us, p, first, count
        One period's events grouped by pixel, as in ``profile.Profile``: (N,) flat event pixel, phase
        (µs, in [0, period_us)), polarity, index of the pixel's first event and its number of events.
    n_pixels
        Number of super pixels (event pixels).
    period_us
        The light period T, µs.
    contrast_pos, contrast_neg
        Thresholds C⁺ and C⁻, log units.
    refractory_us
        The refractory period R, µs, for the compensation α (0: none).
    bounds_us
        (J+1,) phases of the exposure windows' bounds, µs.
    frame_values
        (n_pixels, J) the super pixels' frame values per window (the area mean of their frame pixels,
        in saturation units).
    f, threshold_per_s
        With the events' (N,) interval profile f (eq. 20, log units per second), s changes at events
        with |f| ≥ ``threshold_per_s`` (the paper's rule); without, at the window bounds (one value
        per window).
    device
        Where the scale is fitted: "cpu" with numpy, or a torch device (``irradiance_device``, the same
        to rounding).

    Returns
    -------
    Irradiance
        Knots of L, change points and fitted scale s per super pixel.
    """
    period = float(period_us)
    n = len(t_us)
    local = np.arange(n) - first
    previous = first + np.mod(local - 1, np.maximum(count, 1))
    interval = np.where(count == 1, period, np.mod(t_us - t_us[previous], period))
    contrast = np.where(p > 0, contrast_pos, contrast_neg)
    step = p * contrast + refractory_log_alpha(p, contrast, interval, refractory_us)
    # the first event of a pixel is the origin L = 0; its step closes the cycle
    step_after_first = np.where(local == 0, 0.0, step)
    level = _grouped_cumsum(step_after_first, first)
    drift = np.bincount(pixel, weights=step, minlength=n_pixels)[pixel] if n else np.empty(0)
    level -= drift * (t_us - t_us[first]) / period
    keys, logs = _knots(pixel, t_us, level, first, count, n_pixels, period)
    bounds = np.asarray(bounds_us, dtype=np.float64)
    if f is None:
        changes = np.tile(bounds[:-1], (n_pixels, 1))
    else:
        changes = _change_points(f, t_us, pixel, first, count, threshold_per_s, n_pixels)
    irradiance = Irradiance(keys, logs, changes, np.ones(changes.shape), bounds, period)
    values = np.asarray(frame_values, dtype=np.float64)
    if devices.on_host(device):
        irradiance.scale = _fit_scale(irradiance, values)
    else:
        irradiance.scale = fit_scale_there(irradiance, values, SCALE_SAMPLES, device)
    return irradiance


def _change_points(f: np.ndarray, t_us: np.ndarray, pixel: np.ndarray, first: np.ndarray, count: np.ndarray,
                   threshold: float, n_pixels: int) -> np.ndarray:
    """(n_pixels, MAX_PIECES) phases where s changes, sorted, NaN where a pixel has fewer: the ends
    of each pixel's runs of consecutive events with |f| ≥ ``threshold`` (one abrupt change fires a
    burst), the MAX_PIECES runs with the largest |f| at their end."""
    out = np.full((n_pixels, MAX_PIECES), np.nan)
    strong = np.abs(f) >= threshold
    local = np.arange(len(f)) - first
    after = first + np.mod(local + 1, np.maximum(count, 1))
    ends = np.flatnonzero(strong & (~strong[after] | (count == 1)))
    if ends.size:
        order = ends[np.lexsort((-np.abs(f[ends]), pixel[ends]))]
        group = pixel[order]
        starts = np.flatnonzero(np.r_[True, group[1:] != group[:-1]])
        rank = np.arange(order.size) - np.repeat(starts, np.diff(np.r_[starts, order.size]))
        keep = rank < MAX_PIECES
        out[group[keep], rank[keep]] = t_us[order[keep]]
    return np.sort(out, axis=1)


def _grouped_cumsum(values: np.ndarray, first: np.ndarray) -> np.ndarray:
    """Cumulative sum restarting at each group's first element."""
    total = np.cumsum(values)
    return total - (total[first] - values[first])


def _knots(
    pixel: np.ndarray, t_us: np.ndarray, level: np.ndarray, first: np.ndarray, count: np.ndarray, n_pixels: int, period: float
) -> tuple[np.ndarray, np.ndarray]:
    """Sorted interpolation knots: every event, plus each pixel's last event one period earlier and
    its first one period later (so L wraps), plus flat knots at 0 and T for pixels without events."""
    starts = np.flatnonzero(np.r_[True, pixel[1:] != pixel[:-1]]) if len(pixel) else np.empty(0, np.int64)
    ends = starts + count[starts] - 1
    silent = np.setdiff1d(np.arange(n_pixels), pixel[starts])
    key_pixel = np.concatenate([pixel, pixel[starts], pixel[starts], silent, silent]).astype(np.float64)
    phase = np.concatenate([t_us, t_us[ends] - period, t_us[starts] + period, np.zeros(len(silent)), np.full(len(silent), period)])
    logs = np.concatenate([level, level[ends], level[starts], np.zeros(2 * len(silent))])
    keys = key_pixel * 3.0 * period + period + phase
    order = np.argsort(keys, kind="stable")
    return keys[order], logs[order]


def _fit_scale(irradiance: Irradiance, frame_values: np.ndarray) -> np.ndarray:
    """s per (pixel, piece): the least-squares fit of the midpoint-rule integrals of Î over the
    windows to the frame values (see the module docstring)."""
    n_pixels, n_windows = frame_values.shape
    bounds = irradiance.bounds_us
    pieces = irradiance.change_us.shape[1]
    integrals = np.zeros((n_pixels, n_windows, pieces))
    for j in range(n_windows):
        width = bounds[j + 1] - bounds[j]
        phase = bounds[j] + (np.arange(SCALE_SAMPLES) + 0.5) * width / SCALE_SAMPLES
        dt_s = width / SCALE_SAMPLES / US_PER_S
        for start in range(0, n_pixels, SCALE_BLOCK):
            pix = np.arange(start, min(start + SCALE_BLOCK, n_pixels))
            unscaled = np.exp(irradiance.log_level(np.repeat(pix, SCALE_SAMPLES), np.tile(phase, len(pix)))) * dt_s
            # pixels (B, 1) against the window's phase grid (1, S), shared by all of them: no (B·S, pieces)
            # gather of each pixel's change points per sample
            piece = irradiance.piece(pix[:, None], phase[None, :])
            slot = (np.arange(len(pix))[:, None] * pieces + piece).ravel()
            integrals[pix, j] = np.bincount(slot, weights=unscaled, minlength=len(pix) * pieces).reshape(-1, pieces)
    scale = np.einsum("pmj,pj->pm", np.linalg.pinv(integrals), frame_values)
    # one constant s where the pieces' fit is not physical
    total = integrals.sum(axis=2)
    energy = np.einsum("pj,pj->p", total, total)
    constant = np.einsum("pj,pj->p", total, frame_values) / np.where(energy > 0, energy, 1.0)
    bad = ~np.all(np.isfinite(scale) & (scale >= 0), axis=1)
    scale[bad] = constant[bad, None]
    return scale
