"""What every synthetic hybrid capture shares — the simulator's and the DiLiGenT semi-real
converter's: the sensor and timing options (``CaptureTiming``, the sensors from a preset of
``pstoolkit.sim.sensor`` with single fields overridden), their range checks, and the writing of event
chunks. numpy only, so a converter that needs these loads neither torch nor numba."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, replace
from typing import Any, TypeVar

import psfmt
from psfmt import REFRACTORY_RULES
from pstoolkit._shared.progress import Progress
from pstoolkit.errors import UserError
from pstoolkit.events.rule import REFRACTORY_RULE
from pstoolkit.sim.sensor import (
    FRAME_BIT_DEPTHS,
    MAX_NOISE_HZ,
    MAX_RATE_SPREAD_DECADES,
    SENSOR_PRESETS,
    EventSensor,
    FrameSensor,
    SensorModel,
    preset_fields,
    sensor_preset,
)

# Shortest render step of the event simulation, as a fraction of a light turn: a shadow edge or the
# terminator is resolved to 0.25° of the turn (23 µs at 30 turns/s) instead of ESIM's 1 µs floor, which
# cuts render calls at the same event count (``docs/simulator-tuning.md``); crossings inside a step are
# still placed exactly on the interpolated log-irradiance.
EVENT_MIN_STEP_TURNS = 0.25 / 360.0

T = TypeVar("T", bound="CaptureTiming")

@dataclass
class CaptureTiming:
    """The sensor and timing options every synthetic hybrid capture shares (the simulator's and the
    DiLiGenT semi-real converter's): frame size (pixels, square), event pixels per frame pixel,
    the sensors, long exposures per light period, periods and their length, the seed, and
    ``discrete_lights`` K > 0 for a frames-only capture of K instantaneous lights.

    The sensors: ``sensor_model`` names the preset the fields were taken from (``with_preset``;
    defaults: the ``ideal`` preset); the event sensor's thresholds ``contrast`` (C⁺, and C⁻ unless
    ``contrast_neg``) with their per-pixel spread ``contrast_sigma``, refractory period and rule
    (``pstoolkit.events.rule.REFRACTORY_RULES``), noise rates (``pstoolkit.sim.sensor.EventSensor``);
    the frame sensor's bit depth, black level, full well and read noise
    (``pstoolkit.sim.sensor.FrameSensor``)."""

    size: int = 128
    event_scale: float = 0.5
    sensor_model: str = "ideal"
    contrast: float = 0.15
    contrast_neg: float | None = None
    contrast_sigma: float = 0.0
    refractory_us: float = 2000.0
    refractory_rule: str = REFRACTORY_RULE
    leak_hz: float = 0.0
    shot_noise_hz: float = 0.0
    rate_spread_decades: float = 0.0
    hot_pixel_fraction: float = 0.0
    hot_pixel_hz: float = 0.0
    bit_depth: int = 8
    black_level: float = 0.0
    full_well_e: float = 0.0
    read_noise_e: float = 0.0
    frames: int = 3
    periods: int = 1
    period_ms: float = 1000.0 / 30.0
    seed: int = 0
    discrete_lights: int = 0

    @property
    def period_us(self) -> int:
        return int(round(self.period_ms * 1000.0))

    @property
    def duration_us(self) -> int:
        """All periods, µs."""
        return self.periods * self.period_us

    @property
    def min_step_us(self) -> float:
        """Shortest render step of the event simulation (``EVENT_MIN_STEP_TURNS`` of a turn, ≥ 1 µs)."""
        return max(1.0, self.period_us * EVENT_MIN_STEP_TURNS)

    @classmethod
    def with_preset(cls: type[T], preset: str, **fields: Any) -> T:
        """The options of sensor preset ``preset`` (``pstoolkit.sim.sensor.SENSOR_PRESETS``) with
        ``fields`` given (not None) over them; UserError for an unknown preset."""
        chosen = preset_fields(preset)
        chosen.update({k: v for k, v in fields.items() if v is not None})
        return cls(**chosen)

    @property
    def c_neg(self) -> float:
        """C⁻: ``contrast_neg``, or ``contrast`` when None."""
        return self.contrast if self.contrast_neg is None else self.contrast_neg

    def calibration(self) -> psfmt.Calibration:
        """What the capture's ``/calibration`` records of these options: the event→frame affine of the
        event grid, the thresholds, the refractory period and rule, and the sensor model."""
        return psfmt.Calibration(
            event_to_frame=psfmt.scale_affine(self.event_scale),
            contrast_pos=self.contrast,
            contrast_neg=self.c_neg,
            refractory_us=self.refractory_us,
            refractory_rule=self.refractory_rule,
            sensor_model=self.sensor_record(),
        )

    def sensor(self) -> EventSensor:
        """The event sensor both event engines (``pstoolkit.sim.ring_engine.simulate_ring``,
        ``pstoolkit.sim.esim.simulate_events``) take from the capture, seeded by ``seed``."""
        return EventSensor(
            contrast_pos=self.contrast,
            contrast_neg=self.c_neg,
            sigma=self.contrast_sigma,
            refractory_us=self.refractory_us,
            refractory_rule=self.refractory_rule,
            leak_hz=self.leak_hz,
            shot_noise_hz=self.shot_noise_hz,
            rate_spread_decades=self.rate_spread_decades,
            hot_pixel_fraction=self.hot_pixel_fraction,
            hot_pixel_hz=self.hot_pixel_hz,
            seed=self.seed,
        )

    def frame_sensor(self) -> FrameSensor:
        """The frame sensor that quantises the long exposures."""
        return FrameSensor(self.bit_depth, self.black_level, self.full_well_e, self.read_noise_e)

    def sensor_record(self) -> dict[str, Any]:
        """``/calibration/sensor_model`` (spec §9.2): the preset's name — with " (modified)" when a
        field differs from the preset — and the noise figures of both sensors."""
        preset = sensor_preset(self.sensor_model)
        event, frame = self.sensor(), self.frame_sensor()
        same = event == replace(preset.event, seed=self.seed) and frame == preset.frame
        return SensorModel(self.sensor_model + ("" if same else " (modified)"), "", event, frame).record()

    def exposure_bounds_us(self) -> list[int]:
        """Where the long exposures of one period start, then the period's end (µs): ``frames`` equal
        windows tiling the period, rounded to whole µs."""
        return [int(round(k * self.period_us / self.frames)) for k in range(self.frames + 1)]

    def check_with(self, limits: list[tuple[str, bool, str]]) -> None:
        """Raise UserError naming the first option out of range: the shared ones, then ``limits``."""
        if self.sensor_model not in SENSOR_PRESETS:
            raise UserError(f"--sensor {self.sensor_model!r} is not a sensor preset (choose {', '.join(SENSOR_PRESETS)})")
        shared = [
            ("--size", 8 <= self.size <= 8192, "must be between 8 and 8192 pixels"),
            ("--event-scale", 0 < self.event_scale <= 1, "must be in (0, 1] event pixels per frame pixel"),
            ("--periods", 1 <= self.periods <= 10000, "must be between 1 and 10000"),
            ("--contrast", 0.01 <= self.contrast <= 5, "must be between 0.01 and 5"),
            ("--contrast-neg", 0.01 <= self.c_neg <= 5, "must be between 0.01 and 5"),
            ("--contrast-sigma", 0 <= self.contrast_sigma <= 1, "must be between 0 and 1"),
            ("--leak-hz", 0 <= self.leak_hz <= MAX_NOISE_HZ, f"must be between 0 and {MAX_NOISE_HZ:g}"),
            ("--shot-noise-hz", 0 <= self.shot_noise_hz <= MAX_NOISE_HZ, f"must be between 0 and {MAX_NOISE_HZ:g}"),
            ("--rate-spread-decades", 0 <= self.rate_spread_decades <= MAX_RATE_SPREAD_DECADES,
             f"must be between 0 and {MAX_RATE_SPREAD_DECADES:g}"),
            ("--hot-pixel-fraction", 0 <= self.hot_pixel_fraction <= 1, "must be between 0 and 1"),
            ("--hot-pixel-hz", 0 <= self.hot_pixel_hz <= MAX_NOISE_HZ, f"must be between 0 and {MAX_NOISE_HZ:g}"),
            ("--bit-depth", self.bit_depth in FRAME_BIT_DEPTHS, f"must be {', '.join(map(str, list(FRAME_BIT_DEPTHS)[:-1]))} or {list(FRAME_BIT_DEPTHS)[-1]}"),
            ("--black-level", 0 <= self.black_level < 0.5 * (2**self.bit_depth - 1), "must be between 0 and half of saturation"),
            ("--full-well-e", 0 <= self.full_well_e <= 1e9, "must be between 0 and 1e9 electrons"),
            ("--read-noise-e", 0 <= self.read_noise_e <= 1e9, "must be between 0 and 1e9 electrons"),
            ("--read-noise-e", self.read_noise_e == 0 or self.full_well_e > 0, "needs --full-well-e (electrons at saturation)"),
            ("--refractory-us", 0 <= self.refractory_us <= self.period_us, "must be between 0 and the period"),
            ("--refractory-rule", self.refractory_rule in REFRACTORY_RULES, f"must be {' or '.join(REFRACTORY_RULES)}"),
            ("--seed", 0 <= self.seed < 2**63, "must be a non-negative integer"),
        ]
        check_limits(self, [*shared, *limits])
        check_event_grid(self.size, self.event_scale)

def check_limits(config: object, limits: list[tuple[str, bool, str]]) -> None:
    """Raise UserError for the first ``(flag, ok, message)`` that is not ok, naming the flag and the
    configured value (the attribute the flag names, ``--period-ms`` → ``period_ms``)."""
    for flag, ok, message in limits:
        if not ok:
            raise UserError(f"{flag} {getattr(config, flag[2:].replace('-', '_'))!r} {message}")

def check_event_grid(size: int, event_scale: float) -> None:
    """UserError unless ``size`` frame pixels at ``event_scale`` make a whole number of event pixels."""
    pixels = size * event_scale
    if abs(pixels - round(pixels)) > 1e-9:
        raise UserError(f"--size {size} × --event-scale {event_scale:g} = {pixels:g} is not a whole number of event pixels")

def append_event_chunks(
    writer: psfmt.CaptureWriter,
    event_size: tuple[int, int],
    chunks: Iterable[tuple[psfmt.EventArray, float]],
    t1_us: float,
    report: Progress,
) -> int:
    """Start the writer's events for a sensor of ``event_size`` (height, width) and append each
    (events, time reached in µs) of ``chunks``, reporting the share of ``t1_us`` reached; returns the
    number of events."""
    height, width = event_size
    writer.begin_events(width, height)
    count = 0
    for events, t_us in chunks:
        if len(events):
            writer.append_events(events)
            count += len(events)
        report(min(1.0, t_us / t1_us), "events")
    report(1.0, "events")
    return count
