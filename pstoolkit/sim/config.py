"""What decides a simulated capture: ``SimulationConfig`` and its value sets (``BIT_DEPTHS``,
``AUTO_GAINS``). numpy only, so that ``pstoolkit simulate --help`` shows the defaults without
loading torch or numba (the simulator, ``pstoolkit.sim.simulator``, imports them from here)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from pstoolkit.optics.layouts import RING, layout_lights
from pstoolkit.sim.renderers import OWN
from pstoolkit.sim.sensor import FRAME_BIT_DEPTHS, FrameSensor
from pstoolkit.sim.timing import CaptureTiming

BIT_DEPTHS = FRAME_BIT_DEPTHS
AUTO_GAINS = ("diffuse", "peak")
"""What the automatic gain puts at ``DIFFUSE_LEVEL`` of saturation: the brightest diffuse value of any
frame (highlights may clip) or the brightest value of all (nothing clips)."""


@dataclass
class SimulationConfig(CaptureTiming):
    """Everything that decides a simulated capture (``CaptureTiming`` and the scene, light, sensor and
    renderer). ``scene_options`` are ``key=value`` strings checked against the scene's typed options;
    ``lights`` is the layout of a classic capture (``pstoolkit.optics.layouts``: ``ring``, ``grid`` or a
    light-table path; anything but ``ring`` writes a classic capture of all its K lights, and
    ``discrete_lights`` must then be K or 0); ``noise`` is a shorthand for the frame sensor's noise:
    read noise of that fraction of saturation with the shot noise of a full well of 1/noise² electrons,
    over ``full_well_e`` and ``read_noise_e`` (0 = those);
    ``exposure_gain`` (pixel units per irradiance·second) overrides the automatic gain, which
    ``auto_gain`` (``AUTO_GAINS``) sets from the brightest diffuse or the brightest value.
    ``renderer`` is ``own`` (the built-in engines, which use ``brdf``, ``shadows`` and ``device``) or
    an independent renderer of the ``renderers`` registry with its ``renderer_options``
    (``key=value``), which renders a hybrid capture's key images every ``key_step_deg`` of the turn
    (``pstoolkit.sim.keyed``)."""

    scene: str = "sphere"
    scene_options: list[str] = field(default_factory=list)
    lights: str = RING
    elevation_deg: float = 45.0
    noise: float = 0.0
    brdf: str = "ggx"
    exposure_gain: float | None = None
    auto_gain: str = AUTO_GAINS[0]
    shadows: bool = True
    device: str = "cpu"
    renderer: str = OWN
    renderer_options: list[str] = field(default_factory=list)
    key_step_deg: float = 2.0

    def frame_sensor(self) -> FrameSensor:
        """``CaptureTiming.frame_sensor``, its noise set by ``noise`` when that is given."""
        sensor = super().frame_sensor()
        if self.noise == 0:
            return sensor
        return replace(sensor, full_well_e=1.0 / (self.noise * self.noise), read_noise_e=1.0 / self.noise)

    @property
    def discrete(self) -> bool:
        """Whether the capture is a classic one (instantaneous lights, no events)."""
        return self.discrete_lights > 0 or self.lights != RING

    def check(self) -> None:
        """Raise UserError naming the first option out of range (a light-table file is read)."""
        limits: list[tuple[str, bool, str]] = [
            ("--frames", 1 <= self.frames <= 1000, "must be between 1 and 1000"),
            ("--discrete-lights", 0 <= self.discrete_lights <= 10000, "must be between 0 (hybrid capture) and 10000"),
            ("--period-ms", self.period_us >= 10 * max(self.frames, 1), "is too short for the frames (at least 10 µs per frame)"),
            ("--elevation-deg", 0 < self.elevation_deg <= 90, "must be in (0, 90] degrees"),
            ("--noise", 0 <= self.noise <= 0.5, "must be between 0 and 0.5"),
            ("--auto-gain", self.auto_gain in AUTO_GAINS, f"must be {' or '.join(AUTO_GAINS)}"),
            ("--key-step-deg", 0.1 <= self.key_step_deg <= 30, "must be between 0.1 and 30 degrees"),
        ]
        layout = layout_lights(self.lights)
        if layout is not None:
            k = len(layout[0])
            limits.append(("--lights", k <= 10000, f"holds {k} lights, more than the 10000 of a capture"))
            limits.append(("--discrete-lights", self.discrete_lights in (0, k), f"must be {k} or 0 (all of them) with --lights {self.lights}"))
        if self.exposure_gain is not None:
            limits.append(("--exposure-gain", self.exposure_gain > 0, "must be positive"))
        self.check_with(limits)
