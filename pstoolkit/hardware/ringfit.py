"""The ring light's parameters from light directions measured along its turn (non-linear least squares).

Observations are times ``t_us`` (N,) and unit directions ``l`` (N, 3) towards the light (camera
frame: x right, y up, z towards the camera), e.g. a chrome sphere's highlight tracked through the
events. ``fit_ring`` fits the ``ring`` model (elevation, phase, period; the sense from the sign of
the turn); ``fit_near_ring`` the ``near-ring`` model (radius and height of the ring in mm as well),
which needs where on the target each direction was seen (``points_mm``, (N, 3)): a point light's
direction changes with the point, so a target off the ring's axis tells radius and height apart.
Both start from the unwrapped azimuth's straight line, use a soft-L1 loss so that a few bad
windows do not pull the fit, and report the RMS and largest angle between model and data.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pstoolkit.errors import UserError
from pstoolkit.optics.lights import NearRingLight, RingLight

MIN_OBSERVATIONS = 6
LOSS_SCALE = 0.01
"""Residuals (unit-vector differences, ≈ radians) beyond this count linearly, not quadratically."""


@dataclass
class RingFit:
    """A fitted model and its residual angles: RMS and max over all observations, in degrees."""

    light: RingLight | NearRingLight
    rms_deg: float
    max_deg: float
    observations: int


def angles_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angles (N,) in degrees between unit vectors (N, 3)."""
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=-1), -1.0, 1.0)))


def _start(t_us: np.ndarray, l: np.ndarray) -> tuple[float, float, int, float]:
    """Phase (deg), period (µs), sense and elevation (deg) from the azimuth's straight line."""
    if len(t_us) < MIN_OBSERVATIONS:
        raise UserError(f"light calibration: {len(t_us)} highlight positions, at least {MIN_OBSERVATIONS} are needed to fit a ring")
    order = np.argsort(t_us)
    t, d = t_us[order], l[order]
    azimuth = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
    slope, intercept = np.polyfit(t, azimuth, 1)
    if slope == 0 or not np.isfinite(slope):
        raise UserError("light calibration: the highlight does not move around the sphere")
    elevation = float(np.degrees(np.mean(np.arcsin(np.clip(d[:, 2], -1.0, 1.0)))))
    return float(np.degrees(intercept)) % 360.0, float(2.0 * np.pi / abs(slope)), int(np.sign(slope)), elevation


def _finish(light: RingLight | NearRingLight, t_us: np.ndarray, l: np.ndarray, points_mm: np.ndarray | None) -> RingFit:
    if points_mm is None:
        model, _ = light.evaluate(t_us)
    else:
        model = _near_directions(light, t_us, points_mm)  # type: ignore[arg-type]
    error = angles_deg(model, l)
    return RingFit(light, float(np.sqrt(np.mean(error**2))), float(error.max()), len(t_us))


def fit_ring(t_us: np.ndarray, l: np.ndarray) -> RingFit:
    """The ``ring`` model (t0 = 0) that best explains directions ``l`` (N, 3) at ``t_us`` (N,)."""
    from scipy.optimize import least_squares  # deferred: scipy loads only for calibration

    t = np.asarray(t_us, dtype=np.float64)
    d = np.asarray(l, dtype=np.float64)
    phase, period, sense, elevation = _start(t, d)

    def residual(x: np.ndarray) -> np.ndarray:
        e, phi = np.radians(x[0]), np.radians(x[1]) + sense * 2.0 * np.pi * t / x[2]
        model = np.stack([np.cos(e) * np.cos(phi), np.cos(e) * np.sin(phi), np.full_like(phi, np.sin(e))], axis=-1)
        return (model - d).ravel()

    x0 = np.array([elevation, phase, period])
    result = least_squares(residual, x0, x_scale=np.array([1.0, 1.0, period * 1e-3]), loss="soft_l1", f_scale=LOSS_SCALE)
    e, phase, period = result.x
    light = RingLight(elevation_deg=float(e), period_us=float(abs(period)), phase_deg=float(phase) % 360.0, sense=sense)
    return _finish(light, t, d, None)


def _near_directions(light: NearRingLight, t_us: np.ndarray, points_mm: np.ndarray) -> np.ndarray:
    """Direction (N, 3) of a near light at time t_us[i] seen from points_mm[i]."""
    offset = light.position_mm(t_us) - points_mm
    return offset / np.linalg.norm(offset, axis=-1, keepdims=True)


def fit_near_ring(
    t_us: np.ndarray, l: np.ndarray, points_mm: np.ndarray, pixel_pitch_mm: float, center_px: np.ndarray | None = None,
    radius_mm: float | None = None,
) -> RingFit:
    """The ``near-ring`` model (t0 = 0) that best explains directions ``l`` (N, 3) seen from
    ``points_mm`` (N, 3) at ``t_us`` (N,); ``pixel_pitch_mm`` and ``center_px`` are carried into the
    model. ``radius_mm`` is the first guess of the ring's radius (default: 10× the spread of the
    points); the height starts at the far-field elevation's."""
    from scipy.optimize import least_squares

    t = np.asarray(t_us, dtype=np.float64)
    d = np.asarray(l, dtype=np.float64)
    x_mm = np.asarray(points_mm, dtype=np.float64)
    far = fit_ring(t, d).light
    assert isinstance(far, RingLight)
    spread = float(np.ptp(x_mm[:, :2], axis=0).max()) if len(x_mm) > 1 else 1.0
    r0 = radius_mm if radius_mm is not None else 10.0 * max(spread, 1e-3)
    h0 = r0 * np.tan(np.radians(np.clip(far.elevation_deg, 1.0, 89.0)))

    def residual(x: np.ndarray) -> np.ndarray:
        r, h, phase, period = x
        phi = np.radians(phase) + far.sense * 2.0 * np.pi * t / period
        offset = np.stack([r * np.cos(phi), r * np.sin(phi), np.full_like(phi, h)], axis=-1) - x_mm
        return (offset / np.linalg.norm(offset, axis=-1, keepdims=True) - d).ravel()

    x0 = np.array([r0, h0, far.phase_deg, far.period_us])
    result = least_squares(
        residual, x0, x_scale=np.array([r0, h0, 1.0, far.period_us * 1e-3]), bounds=([1e-6, 1e-6, -np.inf, 1.0], np.inf),
        loss="soft_l1", f_scale=LOSS_SCALE,
    )
    r, h, phase, period = result.x
    light = NearRingLight(
        radius_mm=float(r), height_mm=float(h), pixel_pitch_mm=pixel_pitch_mm, period_us=float(period),
        phase_deg=float(phase) % 360.0, sense=far.sense, center_px=center_px,
    )
    return _finish(light, t, d, x_mm)
