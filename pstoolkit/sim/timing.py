"""What every synthetic hybrid capture shares — the simulator's and the DiLiGenT semi-real
converter's: the sensor and timing options (``CaptureTiming``), their range checks, and the writing of
event chunks. numpy only, so a converter that needs these loads neither torch nor numba."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import psfmt
from pstoolkit.errors import UserError
from pstoolkit.events.rule import REFRACTORY_RULE, REFRACTORY_RULES
from pstoolkit.sim.sensor import EventSensor
from pstoolkit.solve.base import Progress

# Shortest render step of the event simulation, as a fraction of a light turn: a shadow edge or the
# terminator is resolved to 0.25° of the turn (23 µs at 30 turns/s) instead of ESIM's 1 µs floor, which
# cuts render calls at the same event count (``docs/simulator-tuning.md``); crossings inside a step are
# still placed exactly on the interpolated log-irradiance.
EVENT_MIN_STEP_TURNS = 0.25 / 360.0

@dataclass
class CaptureTiming:
    """The sensor and timing options every synthetic hybrid capture shares (the simulator's and the
    DiLiGenT semi-real converter's): frame size (pixels, square), event pixels per frame pixel,
    contrast threshold, refractory period and rule (``pstoolkit.events.rule.REFRACTORY_RULES``), long exposures
    per light period, periods and their length, the seed, and ``discrete_lights`` K > 0 for a
    frames-only capture of K instantaneous lights."""

    size: int = 128
    event_scale: float = 0.5
    contrast: float = 0.15
    refractory_us: float = 2000.0
    refractory_rule: str = REFRACTORY_RULE
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

    def calibration(self) -> psfmt.Calibration:
        """What the capture's ``/calibration`` records of these options: the event→frame affine of the
        event grid, the symmetric contrast, the refractory period and rule."""
        return psfmt.Calibration(
            event_to_frame=psfmt.scale_affine(self.event_scale),
            contrast_pos=self.contrast,
            contrast_neg=self.contrast,
            refractory_us=self.refractory_us,
            refractory_rule=self.refractory_rule,
        )

    def sensor(self) -> EventSensor:
        """The event sensor both event engines (``pstoolkit.sim.ring_engine.simulate_ring``,
        ``pstoolkit.sim.esim.simulate_events``) take from the capture: symmetric contrast, refractory
        period and rule, and seed."""
        return EventSensor(
            contrast_pos=self.contrast,
            contrast_neg=self.contrast,
            refractory_us=self.refractory_us,
            refractory_rule=self.refractory_rule,
            seed=self.seed,
        )

    def exposure_bounds_us(self) -> list[int]:
        """Where the long exposures of one period start, then the period's end (µs): ``frames`` equal
        windows tiling the period, rounded to whole µs."""
        return [int(round(k * self.period_us / self.frames)) for k in range(self.frames + 1)]

    def check_with(self, limits: list[tuple[str, bool, str]]) -> None:
        """Raise UserError naming the first option out of range: the shared ones, then ``limits``."""
        shared = [
            ("--size", 8 <= self.size <= 8192, "must be between 8 and 8192 pixels"),
            ("--event-scale", 0 < self.event_scale <= 1, "must be in (0, 1] event pixels per frame pixel"),
            ("--periods", 1 <= self.periods <= 10000, "must be between 1 and 10000"),
            ("--contrast", 0.01 <= self.contrast <= 5, "must be between 0.01 and 5"),
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
