"""The event sensor both event engines simulate (``pstoolkit.sim.esim.simulate_events`` and
``pstoolkit.sim.ring_engine.simulate_ring``): its contrast thresholds and their spread, the refractory
period and rule, the ε of ``L = ln(I + ε)``, the noise rates and the seed of its random draws."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pstoolkit.errors import UserError
from pstoolkit.events.rule import LOG_EPS, REFRACTORY_RULE, REFRACTORY_RULES, check_rule

# Smallest contrast threshold a pixel draws: a spread (``sigma``) cannot give a pixel that fires on noise.
MIN_CONTRAST = 0.01


@dataclass(frozen=True)
class EventSensor:
    """An event sensor (see ``pstoolkit.events.rule`` for the rule it fires by).

    Parameters
    ----------
    contrast_pos, contrast_neg
        Thresholds C⁺ and C⁻ on the change of ``L = ln(I + eps)`` (> 0).
    sigma
        Spread of the per-pixel thresholds, each drawn once from ``N(C, sigma)`` and clamped to
        ≥ ``MIN_CONTRAST`` (≥ 0).
    refractory_us
        Dead time after an event, µs (≥ 0).
    refractory_rule
        What happens in the dead time, one of ``pstoolkit.events.rule.REFRACTORY_RULES``; with
        ``refractory_us`` = 0 both are ESIM's rule.
    eps
        ε of the log irradiance (default ``pstoolkit.events.rule.LOG_EPS``, for irradiance normalised to
        ≈ 1 when bright).
    leak_hz, shot_noise_hz
        Noise rates per pixel (``pstoolkit.sim.esim`` only; the ring engine has no noise).
    seed
        Seed of the thresholds, the leak's start and the shot noise (``rngs``).
    """

    contrast_pos: float = 0.15
    contrast_neg: float = 0.15
    sigma: float = 0.0
    refractory_us: float = 0.0
    refractory_rule: str = REFRACTORY_RULE
    eps: float = LOG_EPS
    leak_hz: float = 0.0
    shot_noise_hz: float = 0.0
    seed: int = 0

    @property
    def paced(self) -> bool:
        """Whether the sensor fires by the "rate-limited" rule (a refractory period under it; with none,
        both rules are "reset-at-end")."""
        return self.refractory_rule == REFRACTORY_RULES[1] and self.refractory_us > 0

    @property
    def noisy(self) -> bool:
        """Whether the sensor leaks or has shot noise."""
        return self.leak_hz > 0 or self.shot_noise_hz > 0

    def half_contrast(self) -> float:
        """Half the smaller threshold: the engines' default largest change of L between samples."""
        return 0.5 * min(self.contrast_pos, self.contrast_neg)

    def check(self, caller: str) -> None:
        """UserError naming the first field out of range, prefixed with ``caller``."""
        for name in ("contrast_pos", "contrast_neg", "eps"):
            value = getattr(self, name)
            if not value > 0 or not math.isfinite(value):
                raise UserError(f"{caller}: {name} must be a positive number, got {value}")
        for name in ("sigma", "refractory_us", "shot_noise_hz", "leak_hz"):
            value = getattr(self, name)
            if not value >= 0 or not math.isfinite(value):
                raise UserError(f"{caller}: {name} must be zero or positive, got {value}")
        check_rule(self.refractory_rule, caller)

    def rngs(self) -> tuple[np.random.Generator, np.random.Generator, np.random.Generator]:
        """The independent random streams of the sensor's ``seed``: thresholds, leak, shot noise."""
        thresholds, leak, shot = (np.random.default_rng(s) for s in np.random.SeedSequence(self.seed).spawn(3))
        return thresholds, leak, shot

    def thresholds(self, n_pixels: int) -> tuple[np.ndarray, np.ndarray]:
        """Per-pixel thresholds C⁺ and C⁻ (``n_pixels``,), each ``N(C, sigma)`` clamped to ≥
        ``MIN_CONTRAST``, from the first of ``rngs``; both engines draw the same for the same sensor."""
        if self.sigma == 0:
            return (np.full(n_pixels, max(self.contrast_pos, MIN_CONTRAST)),
                    np.full(n_pixels, max(self.contrast_neg, MIN_CONTRAST)))
        rng = self.rngs()[0]
        return tuple(np.maximum(rng.normal(c, self.sigma, n_pixels), MIN_CONTRAST)  # type: ignore[return-value]
                     for c in (self.contrast_pos, self.contrast_neg))


def check_sampling(
    caller: str, t0_us: float, t1_us: float, width: int, height: int, steps: dict[str, float], chunk_samples: int = 2,
) -> None:
    """Check the sampling options of an event engine; returns nothing when all are in range.

    Parameters
    ----------
    caller
        Name of the engine, prefixed to the message.
    t0_us, t1_us
        The span simulated, µs (t1_us > t0_us).
    width, height
        The sensor's size in pixels, 1 to 65536 each.
    steps
        Options by name that must each be a positive finite number (``max_dlog``, ``min_dt_us`` …).
    chunk_samples
        The most times rendered or held at once (≥ 2).

    Raises
    ------
    UserError
        Naming the first option out of range.
    """
    if not t1_us > t0_us:
        raise UserError(f"{caller}: t1_us ({t1_us}) must be after t0_us ({t0_us})")
    if width < 1 or height < 1 or width > 65536 or height > 65536:
        raise UserError(f"{caller}: sensor size {width}x{height} must be 1 to 65536 pixels per side")
    for name, value in steps.items():
        if not value > 0 or not math.isfinite(value):
            raise UserError(f"{caller}: {name} must be a positive number, got {value}")
    if chunk_samples < 2:
        raise UserError(f"{caller}: chunk_samples must be at least 2, got {chunk_samples}")
