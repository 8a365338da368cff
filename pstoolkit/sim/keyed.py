"""Captures from key images: irradiance known at key times of a light period and interpolated in
between, log-linearly per pixel (``L = ln(I + ε)`` linear in time), which gives long exposures in
closed form (``window_mean``) and a render callback for the event simulation (``event_render``).

Shared by the DiLiGenT semi-real converter (its key images are a dataset's photographs) and the
simulator's independent renderers (``pstoolkit.sim.renderers``: key images rendered every
``key_step_deg`` of the turn, ``key_times_us``).

Error of the interpolation: where the irradiance is smooth in the light direction, L between keys
deviates from the truth by about h²/8·|L''| for a step of h radians; a pixel crossing an attached or
cast shadow boundary between two keys sees the step spread over the step's time, so its events and
its exposure shift by at most one step (on average half a step) of the turn.

    knots = key_times_us(period_us, 180)                 # (181,) int64, ends with the period
    log_keys = log_irradiance(images)                    # (180, H, W, 3) key images, logged
    frame = window_mean(log_keys, knots, 0, period_us / 3)
    render = event_render(log_grey_keys, knots, period_us)   # render(t_us) -> (T, He, We)
"""

from __future__ import annotations

import numpy as np
from scipy.special import exprel

from pstoolkit.events.rule import LOG_EPS
from pstoolkit.sim.esim import Render


def key_times_us(period_us: int, keys: int) -> np.ndarray:
    """(keys + 1,) int64: ``keys`` key times spread evenly over the period from 0, rounded to µs,
    then the period's end."""
    return np.round(np.arange(keys + 1) * period_us / keys).astype(np.int64)


def window_mean(log_keys: np.ndarray, knots_us: np.ndarray, t0_us: float, t1_us: float) -> np.ndarray:
    """Mean irradiance exp(L(t)) − ε over [t0_us, t1_us) ⊂ [knots_us[0], knots_us[-1]], L linear in
    time from ``log_keys[j]`` to ``log_keys[j + 1]`` (the last key wraps to the first); shape
    ``log_keys.shape[1:]``."""
    log_next = np.roll(log_keys, -1, axis=0)
    total = np.zeros(log_keys.shape[1:])
    for j in range(len(log_keys)):
        s0, s1 = max(t0_us, knots_us[j]), min(t1_us, knots_us[j + 1])
        if s1 <= s0:
            continue
        span = float(knots_us[j + 1] - knots_us[j])
        slope = log_next[j] - log_keys[j]
        w0, w1 = (s0 - knots_us[j]) / span, (s1 - knots_us[j]) / span
        # ∫ exp(a + w·d) dw over [w0, w1] = (w1 − w0)·exp(a + w0·d)·exprel((w1 − w0)·d), stable as d → 0
        total += span * (w1 - w0) * np.exp(log_keys[j] + w0 * slope) * exprel((w1 - w0) * slope)
    return total / (t1_us - t0_us) - LOG_EPS


def event_render(log_keys: np.ndarray, knots_us: np.ndarray, period_us: int) -> Render:
    """The render callback of the event generator: irradiance whose log runs linearly between the
    key logs (M, He, We), periodic in ``period_us``."""
    log_next = np.roll(log_keys, -1, axis=0)
    starts = knots_us[:-1].astype(np.float64)
    spans = np.diff(knots_us).astype(np.float64)

    def render(t_us: np.ndarray) -> np.ndarray:
        tau = np.mod(np.asarray(t_us, dtype=np.float64), period_us)
        j = np.clip(np.searchsorted(starts, tau, side="right") - 1, 0, len(starts) - 1)
        w = ((tau - starts[j]) / spans[j])[:, None, None]
        return np.maximum(np.exp((1.0 - w) * log_keys[j] + w * log_next[j]) - LOG_EPS, 0.0)

    return render
