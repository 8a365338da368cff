"""The event-camera rule shared by the simulator (``pstoolkit.esim``) and the event-based solvers.

A pixel sees the log-irradiance ``L(t) = ln(I(t) + ε)`` (``I`` linear grey irradiance, ``ε`` =
``LOG_EPS`` unless stated) and keeps a reference level ``L_ref``. It fires event ``k`` at ``t_k`` with
polarity ``p_k = +1`` when ``L`` has risen ``C⁺`` above the reference, ``p_k = −1`` when it has fallen
``C⁻`` below it:

    L(t_k) = L_ref,k + p_k · C^{p_k}

Refractory rule (``REFRACTORY_RULE = "reset-at-end"``, the rule of the DualResPS paper, eq. 6, with
``η`` the refractory period ``R``): after an event at ``t`` the pixel is blind until ``t + R``; nothing
it would have seen in between is emitted, and at ``t + R`` its reference is reset to the level it
sees then. Hence

    L_ref,1 = L(t_start)          (the level when the simulation starts)
    L_ref,k = L(t_{k-1} + R)      for k ≥ 2

With ``R = 0`` this is ESIM's rule (the reference moves to the crossed level). A solver relating
consecutive events of a pixel therefore evaluates the earlier level at ``reference_time_us(t_prev,
R)``, not at ``t_prev``. ``ε = 1e-3`` assumes irradiance normalised to about 1 for a bright pixel
(the 99th-percentile normalisation of the semi-real recipe): the log stays finite in attached shadow
(``ln ε ≈ −6.9``) while shifting a lit pixel's log level by less than 0.1 %.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

GREY_WEIGHTS = (0.299, 0.587, 0.114)
"""Rec. 601 luma: the grey an event sensor (and a grey solve) sees of linear RGB (facts §3)."""

from psfmt import EventArray

LOG_EPS = 1e-3
REFRACTORY_RULE = "reset-at-end"


def log_irradiance(irradiance: np.ndarray, eps: float = LOG_EPS, dtype: type = np.float64) -> np.ndarray:
    """``ln(I + ε)``, the quantity whose changes fire events, computed in ``dtype``."""
    return np.log(np.asarray(irradiance, dtype=dtype) + dtype(eps))


def reference_time_us(t_prev_us: np.ndarray, refractory_us: float) -> np.ndarray:
    """When the reference level of the event after one at ``t_prev_us`` was taken: ``t_prev + R`` (µs)."""
    return np.asarray(t_prev_us, dtype=np.float64) + float(refractory_us)


@dataclass
class EventPairs:
    """Consecutive events of the same pixel: ``pixel`` = y·width + x, the earlier event's time
    ``t_prev_us``, the later event's time ``t_us`` and polarity ``p``; grouped by pixel, in time
    order within a pixel."""

    pixel: np.ndarray
    t_prev_us: np.ndarray
    t_us: np.ndarray
    p: np.ndarray


def consecutive_pairs(events: EventArray, width: int) -> EventPairs:
    """Every (previous, current) event pair of each pixel of a time-sorted stream; a pixel's first
    event has no pair (its reference is the level at the start of the recording)."""
    pixel = events.y.astype(np.int64) * width + events.x.astype(np.int64)
    # A stable sort by pixel keeps each pixel's events in time order.
    order = np.argsort(pixel, kind="stable")
    pixel, t, p = pixel[order], events.t[order], events.p[order]
    same = pixel[1:] == pixel[:-1]
    return EventPairs(pixel=pixel[1:][same], t_prev_us=t[:-1][same], t_us=t[1:][same], p=p[1:][same])
