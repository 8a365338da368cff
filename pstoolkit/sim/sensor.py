"""The sensors a synthetic capture is made with: the event sensor both event engines simulate
(``EventSensor``: ``pstoolkit.sim.esim.simulate_events`` and ``pstoolkit.sim.ring_engine.simulate_ring``),
the frame sensor that quantises the long exposures (``FrameSensor``), and named presets of both
(``sensor_preset``: ``ideal``, ``evk4``, ``davis346``; figures and sources in docs/sensors.md)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from psfmt import REFRACTORY_RULES
from pstoolkit.errors import UserError
from pstoolkit.events.rule import LOG_EPS, REFRACTORY_RULE, check_rule

# Smallest contrast threshold a pixel draws: a spread (``sigma``) cannot give a pixel that fires on noise.
MIN_CONTRAST = 0.01
# Shot-noise rate of a bright pixel (irradiance ≥ 1) as a share of the dark rate; in between it falls
# linearly with the irradiance (v2e's SHOT_NOISE_INTEN_FACTOR).
SHOT_NOISE_BRIGHT_FACTOR = 0.25
# Highest noise rate per pixel accepted (leak, shot, hot pixels), Hz: 1 MHz is one event per µs.
MAX_NOISE_HZ = 1e6
# Most decades of per-pixel spread of the noise rates.
MAX_RATE_SPREAD_DECADES = 2.0


@dataclass(frozen=True)
class EventSensor:
    """An event sensor (see ``pstoolkit.events.rule`` for the rule it fires by, docs/sensors.md for
    the noise models, after v2e: Hu, Liu & Delbruck 2021).

    Parameters
    ----------
    contrast_pos, contrast_neg
        Thresholds C⁺ and C⁻ on the change of ``L = ln(I + eps)`` (> 0).
    sigma
        Spread of the per-pixel thresholds, each drawn once from ``N(C, sigma)`` and clamped to
        ≥ ``MIN_CONTRAST`` (≥ 0; ESIM's threshold mismatch).
    refractory_us
        Dead time after an event, µs (≥ 0).
    refractory_rule
        What happens in the dead time, one of ``pstoolkit.events.rule.REFRACTORY_RULES``; with
        ``refractory_us`` = 0 both are ESIM's rule.
    eps
        ε of the log irradiance (default ``pstoolkit.events.rule.LOG_EPS``, for irradiance normalised to
        ≈ 1 when bright).
    leak_hz
        Leak (background activity): each pixel's reference drifts down by its C⁺ every 1/rate s, so a
        static pixel fires positive events at its rate; they are threshold crossings like any other
        and follow the refractory rule. The start of each pixel's drift is a uniform random fraction
        of C⁺, so static pixels do not fire in lockstep.
    shot_noise_hz
        Shot-noise events per pixel and second in the dark, ±1 with equal odds; a pixel of irradiance
        ``I`` fires them at ``rate·(1 − (1 − SHOT_NOISE_BRIGHT_FACTOR)·min(I, 1))`` and a pixel of
        lower threshold more often (× nominal C / the pixel's C of that polarity, as v2e).
    rate_spread_decades
        Spread of the per-pixel leak and shot-noise rates: each pixel's rates are the nominal ones times
        ``10**N(0, rate_spread_decades)`` (v2e's ``noise_rate_cov_decades``; ≥ 0).
    hot_pixel_fraction, hot_pixel_hz
        A share of pixels (drawn once) that fire ±1 events at ``hot_pixel_hz`` whatever they see.
    seed
        Seed of every random draw (``rngs``).

    Shot-noise and hot-pixel events obey the refractory period: one that falls within ``refractory_us``
    of the pixel's previous event (signal or noise) is not emitted. They do not move the pixel's
    reference level nor blind its signal (``pstoolkit.sim.event_noise``).
    """

    contrast_pos: float = 0.15
    contrast_neg: float = 0.15
    sigma: float = 0.0
    refractory_us: float = 0.0
    refractory_rule: str = REFRACTORY_RULE
    eps: float = LOG_EPS
    leak_hz: float = 0.0
    shot_noise_hz: float = 0.0
    rate_spread_decades: float = 0.0
    hot_pixel_fraction: float = 0.0
    hot_pixel_hz: float = 0.0
    seed: int = 0

    @property
    def paced(self) -> bool:
        """Whether the sensor fires by the "rate-limited" rule (a refractory period under it; with none,
        both rules are "reset-at-end")."""
        return self.refractory_rule == REFRACTORY_RULES[1] and self.refractory_us > 0

    @property
    def fires_noise(self) -> bool:
        """Whether the sensor fires events of its own besides crossings (shot noise, hot pixels)."""
        return self.shot_noise_hz > 0 or (self.hot_pixel_fraction > 0 and self.hot_pixel_hz > 0)

    def half_contrast(self) -> float:
        """Half the smaller threshold: the engines' default largest change of L between samples."""
        return 0.5 * min(self.contrast_pos, self.contrast_neg)

    def check(self, caller: str) -> None:
        """UserError naming the first field out of range, prefixed with ``caller``."""
        for name in ("contrast_pos", "contrast_neg", "eps"):
            value = getattr(self, name)
            if not value > 0 or not math.isfinite(value):
                raise UserError(f"{caller}: {name} must be a positive number, got {value}")
        for name in ("sigma", "refractory_us", "shot_noise_hz", "leak_hz", "rate_spread_decades", "hot_pixel_hz",
                     "hot_pixel_fraction"):
            value = getattr(self, name)
            if not value >= 0 or not math.isfinite(value):
                raise UserError(f"{caller}: {name} must be zero or positive, got {value}")
        for name in ("shot_noise_hz", "leak_hz", "hot_pixel_hz"):
            if getattr(self, name) > MAX_NOISE_HZ:
                raise UserError(f"{caller}: {name} must be at most {MAX_NOISE_HZ:g} Hz, got {getattr(self, name)}")
        if self.hot_pixel_fraction > 1:
            raise UserError(f"{caller}: hot_pixel_fraction must be between 0 and 1, got {self.hot_pixel_fraction}")
        if self.rate_spread_decades > MAX_RATE_SPREAD_DECADES:
            raise UserError(f"{caller}: rate_spread_decades must be at most {MAX_RATE_SPREAD_DECADES:g}, got {self.rate_spread_decades}")
        check_rule(self.refractory_rule, caller)

    def rngs(self) -> tuple[np.random.Generator, ...]:
        """The independent random streams of the sensor's ``seed``: thresholds, leak (start levels and
        per-pixel rates), shot noise, hot pixels."""
        return tuple(np.random.default_rng(s) for s in np.random.SeedSequence(self.seed).spawn(4))

    def thresholds(self, n_pixels: int) -> tuple[np.ndarray, np.ndarray]:
        """Per-pixel thresholds C⁺ and C⁻ (``n_pixels``,), each ``N(C, sigma)`` clamped to ≥
        ``MIN_CONTRAST``, from the first of ``rngs``; both engines draw the same for the same sensor."""
        if self.sigma == 0:
            return (np.full(n_pixels, max(self.contrast_pos, MIN_CONTRAST)),
                    np.full(n_pixels, max(self.contrast_neg, MIN_CONTRAST)))
        rng = self.rngs()[0]
        return tuple(np.maximum(rng.normal(c, self.sigma, n_pixels), MIN_CONTRAST)  # type: ignore[return-value]
                     for c in (self.contrast_pos, self.contrast_neg))

    def rate_factors(self, n_pixels: int) -> np.ndarray:
        """(``n_pixels``,) factors of each pixel's leak and shot-noise rates, ``10**N(0,
        rate_spread_decades)`` (ones without a spread), from the leak stream of ``rngs`` after the
        start levels; both engines draw the same."""
        if self.rate_spread_decades == 0:
            return np.ones(n_pixels)
        rng = self.rngs()[1]
        rng.uniform(0.0, 1.0, n_pixels)  # the start levels (``leak_start``) come first
        return 10.0 ** rng.normal(0.0, self.rate_spread_decades, n_pixels)

    def leak_start(self, c_pos: np.ndarray) -> np.ndarray:
        """(pixels,) how far below its start level each pixel's reference starts: a uniform fraction of
        its C⁺ (zeros without leak), the first draw of the leak stream."""
        if self.leak_hz == 0:
            return np.zeros(c_pos.shape)
        return self.rngs()[1].uniform(0.0, 1.0, c_pos.shape[0]) * c_pos

    def leak_per_us(self, c_pos: np.ndarray) -> np.ndarray:
        """(pixels,) upward drift of each pixel's L against its reference, per µs: its leak rate times
        its C⁺ (zeros without leak)."""
        if self.leak_hz == 0:
            return np.zeros(c_pos.shape)
        return self.leak_hz * 1e-6 * self.rate_factors(c_pos.shape[0]) * c_pos


@dataclass(frozen=True)
class FrameSensor:
    """A linear frame sensor: ``bit_depth`` bits (saturation ``2**bit_depth − 1``), ``black_level``
    (stored value of no light), and — with a full well — photon shot noise and read noise.

    A pixel of signal ``v`` above black (in stored units, 0 to saturation − black) collects
    ``e = v/(saturation − black)·full_well_e`` electrons; the sensor stores
    ``black + (Poisson(e) + N(0, read_noise_e))·(saturation − black)/full_well_e``, rounded and
    clipped to [0, saturation]. ``full_well_e`` = 0: no noise (the ideal sensor)."""

    bit_depth: int = 8
    black_level: float = 0.0
    full_well_e: float = 0.0
    read_noise_e: float = 0.0

    @property
    def saturation(self) -> float:
        return float(2**self.bit_depth - 1)

    @property
    def noisy(self) -> bool:
        return self.full_well_e > 0

    def check(self, caller: str) -> None:
        """UserError naming the first field out of range, prefixed with ``caller``."""
        if self.bit_depth not in FRAME_BIT_DEPTHS:
            raise UserError(f"{caller}: bit_depth must be one of {', '.join(map(str, FRAME_BIT_DEPTHS))}, got {self.bit_depth}")
        if not 0 <= self.black_level < 0.5 * self.saturation:
            raise UserError(f"{caller}: black_level must be between 0 and half of saturation ({self.saturation:g}), got {self.black_level}")
        for name in ("full_well_e", "read_noise_e"):
            value = getattr(self, name)
            if not (value >= 0 and math.isfinite(value)) or value > 1e9:
                raise UserError(f"{caller}: {name} must be between 0 and 1e9 electrons, got {value}")
        if self.read_noise_e > 0 and self.full_well_e == 0:
            raise UserError(f"{caller}: read_noise_e needs full_well_e (electrons at saturation)")

    def signal_range(self) -> float:
        """Stored units from black to saturation."""
        return self.saturation - self.black_level

    def quantise(self, signal: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Stored values of ``signal`` (stored units above black, float): black level, shot and read
        noise, rounded and clipped; dtype ``FRAME_BIT_DEPTHS[bit_depth]``."""
        value = np.asarray(signal, dtype=np.float64)
        if self.noisy:
            per_electron = self.signal_range() / self.full_well_e
            electrons = rng.poisson(np.clip(value, 0.0, None) / per_electron)
            value = electrons * per_electron + rng.normal(0.0, self.read_noise_e * per_electron, value.shape)
        if self.black_level:
            value = value + self.black_level
        return np.clip(np.rint(value), 0.0, self.saturation).astype(FRAME_BIT_DEPTHS[self.bit_depth])


FRAME_BIT_DEPTHS = {8: np.uint8, 10: np.uint16, 12: np.uint16, 16: np.uint16}
"""Bit depths of ``FrameSensor`` and their stored integer types."""


@dataclass(frozen=True)
class SensorModel:
    """A named pair of sensors: the event sensor and the frame sensor of a hybrid capture, with a
    one-line summary (``sensor_preset``)."""

    name: str
    summary: str
    event: EventSensor = field(default_factory=EventSensor)
    frame: FrameSensor = field(default_factory=FrameSensor)

    def record(self) -> dict[str, Any]:
        """What a capture records of the model beyond the thresholds, refractory period and rule (in
        ``/calibration``) and the bit depth and black level (in ``/frames``): the
        ``psfmt.Calibration.sensor_model`` attributes (spec §9.2)."""
        e, f = self.event, self.frame
        return {
            "name": self.name,
            "contrast_sigma": float(e.sigma),
            "leak_hz": float(e.leak_hz),
            "shot_noise_hz": float(e.shot_noise_hz),
            "rate_spread_decades": float(e.rate_spread_decades),
            "hot_pixel_fraction": float(e.hot_pixel_fraction),
            "hot_pixel_hz": float(e.hot_pixel_hz),
            "full_well_e": float(f.full_well_e),
            "read_noise_e": float(f.read_noise_e),
        }


def _evk4() -> SensorModel:
    # Weber contrast 25 % → ln 1.25; the rest as docs/sensors.md says (assumed where sources are silent)
    c = round(math.log(1.25), 4)
    return SensorModel(
        "evk4",
        "Prophesee EVK4 HD (Sony IMX636) with the DualResPS rig's HIK MV-CA050-12UC (Sony IMX264) frame camera",
        EventSensor(contrast_pos=c, contrast_neg=c, sigma=0.03, refractory_us=500.0, refractory_rule=REFRACTORY_RULES[1],
                    leak_hz=0.1, shot_noise_hz=1.0, rate_spread_decades=0.1, hot_pixel_fraction=1e-4, hot_pixel_hz=100.0),
        FrameSensor(bit_depth=12, black_level=64.0, full_well_e=10_500.0, read_noise_e=2.4),
    )


def _davis346() -> SensorModel:
    # Weber contrasts 14.3 % (ON) and 22.5 % (OFF) → ln 1.143, ln 1.225
    return SensorModel(
        "davis346",
        "iniVation DAVIS346: its DVS pixels and its APS (global-shutter) frames",
        EventSensor(contrast_pos=round(math.log(1.143), 4), contrast_neg=round(math.log(1.225), 4), sigma=0.03,
                    refractory_us=500.0, refractory_rule=REFRACTORY_RULES[1], leak_hz=0.1, shot_noise_hz=2.0,
                    rate_spread_decades=0.1, hot_pixel_fraction=1e-3, hot_pixel_hz=50.0),
        FrameSensor(bit_depth=10, black_level=32.0, full_well_e=10_000.0, read_noise_e=14.6),
    )


SENSOR_PRESETS = {
    "ideal": SensorModel(
        "ideal", "noise-free sensors: C = 0.15 both ways, 2 ms reset-at-end refractory, 8-bit frames",
        EventSensor(refractory_us=2000.0), FrameSensor(),
    ),
    "evk4": _evk4(),
    "davis346": _davis346(),
}
"""The named sensor models (``sensor_preset``); docs/sensors.md gives their sources."""


def sensor_preset(name: str) -> SensorModel:
    """The named ``SensorModel`` (``SENSOR_PRESETS``); UserError naming the choices for another name.
    ``replace(model.event, seed=…)`` and ``replace(model.frame, …)`` change single fields."""
    try:
        return SENSOR_PRESETS[name]
    except KeyError:
        raise UserError(f"--sensor {name!r}: not a sensor preset (choose {', '.join(SENSOR_PRESETS)})") from None


def preset_fields(name: str) -> dict[str, Any]:
    """The ``pstoolkit.sim.timing.CaptureTiming`` fields of preset ``name`` (the CLI's options by their
    attribute names), for a caller that overrides some of them."""
    model = sensor_preset(name)
    e, f = model.event, model.frame
    return {
        "sensor_model": model.name,
        "contrast": e.contrast_pos,
        "contrast_neg": e.contrast_neg,
        "contrast_sigma": e.sigma,
        "refractory_us": e.refractory_us,
        "refractory_rule": e.refractory_rule,
        "leak_hz": e.leak_hz,
        "shot_noise_hz": e.shot_noise_hz,
        "rate_spread_decades": e.rate_spread_decades,
        "hot_pixel_fraction": e.hot_pixel_fraction,
        "hot_pixel_hz": e.hot_pixel_hz,
        "bit_depth": f.bit_depth,
        "black_level": f.black_level,
        "full_well_e": f.full_well_e,
        "read_noise_e": f.read_noise_e,
    }


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
