"""Light models: where the light points and how bright it is at any time (and surface point).

A model turns the ``psfmt.LightSpec`` stored in a capture into a vectorised function of time:

    light = build_light_model(capture.lights)
    direction, intensity = light.evaluate(t_us)            # (T, 3) unit vectors, (T, 3) RGB
    direction, intensity = near.evaluate(t_us, points_mm)  # (T, P, 3) each for a near light

Directions are unit vectors from the surface towards the light in the camera frame (x right, y up,
z towards the camera). Times are microseconds (any numeric dtype; computed in float64).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field, fields
from typing import Any, ClassVar

import numpy as np

from psfmt import LightSpec
from pstoolkit._shared.vectors import unit
from pstoolkit.errors import UserError
from pstoolkit.plugin.options import Option

US_PER_S = 1e6
INTERPOLATION = "linear-renormalised"


def _param(spec: LightSpec, key: str) -> Any:
    """The required parameter ``key`` of ``spec``, or a UserError naming the model and the parameter."""
    if key not in spec.params:
        raise UserError(f"light model {spec.model!r}: parameter {key!r} is missing")
    return spec.params[key]


def _scalar(model: str, key: str, value: Any) -> float:
    """A finite float, or a UserError naming the model and the parameter."""
    try:
        number = float(np.asarray(value, dtype=np.float64).reshape(()))
    except (TypeError, ValueError):
        raise UserError(f"light model {model!r}: parameter {key!r} must be a number, got {value!r}") from None
    if not np.isfinite(number):
        raise UserError(f"light model {model!r}: parameter {key!r} must be finite, got {number}")
    return number


def _positive(model: str, key: str, value: Any) -> float:
    number = _scalar(model, key, value)
    if number <= 0:
        raise UserError(f"light model {model!r}: parameter {key!r} must be positive, got {number:g}")
    return number


def _sense(model: str, value: Any) -> int:
    number = _scalar(model, "sense", value)
    if number not in (1.0, -1.0):
        raise UserError(f"light model {model!r}: parameter 'sense' must be +1 or -1, got {number:g}")
    return int(number)


def _array(model: str, key: str, value: Any, shape: tuple[int, ...]) -> np.ndarray:
    """A finite float64 array of ``shape`` (-1 = any length)."""
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise UserError(f"light model {model!r}: parameter {key!r} must be numeric") from None
    if array.ndim != len(shape) or any(s not in (-1, d) for s, d in zip(shape, array.shape)):
        expected = tuple("M" if s < 0 else s for s in shape)
        raise UserError(f"light model {model!r}: parameter {key!r} has shape {array.shape}, expected {expected}")
    if not np.all(np.isfinite(array)):
        raise UserError(f"light model {model!r}: parameter {key!r} holds NaN or infinite values")
    return array



def _ring_angle_rad(t_us: np.ndarray, t0_us: float, period_us: float, phase_deg: float, sense: int) -> np.ndarray:
    # Reduce time modulo the period before scaling, so µs timestamps of long captures keep full precision.
    fraction = np.mod(np.asarray(t_us, dtype=np.float64) - t0_us, period_us) / period_us
    return np.deg2rad(phase_deg) + sense * 2.0 * np.pi * fraction


def _points(model: str, points_mm: np.ndarray | None) -> np.ndarray:
    if points_mm is None:
        raise UserError(f"light model {model!r} is a near light: evaluate it at surface points (points_mm)")
    points = np.asarray(points_mm, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise UserError(f"light model {model!r}: points_mm has shape {points.shape}, expected (P, 3)")
    return points


def _broadcast_directional(
    model: str, direction: np.ndarray, intensity: np.ndarray, points_mm: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray]:
    """A directional light is the same at every point: insert the point axis when points are given."""
    if points_mm is None:
        return direction, intensity
    n = _points(model, points_mm).shape[0]
    shape = direction.shape[:-1] + (n, 3)
    return (
        np.broadcast_to(direction[..., None, :], shape),
        np.broadcast_to(intensity[..., None, :], shape),
    )


class LightModel(ABC):
    """A light trajectory. Subclasses set ``name`` (the registry and file name), ``summary`` (one line),
    ``near`` (True when direction and intensity depend on the surface point) and ``period_us`` (None for
    an aperiodic trajectory). A dataclass subclass inherits the spec round trip (``from_spec``,
    ``to_spec``) from its fields and ``optional_params``; any other defines both."""

    name: ClassVar[str]
    summary: ClassVar[str]
    options: ClassVar[tuple[Option, ...]] = ()
    near: ClassVar[bool] = False
    optional_params: ClassVar[tuple[str, ...]] = ()
    """Fields a stored spec may leave out; the format requires the others, defaults or not."""
    period_us: float | None

    @classmethod
    def from_spec(cls, spec: LightSpec) -> LightModel:
        """Build the model from the parameters stored in a capture (UserError on missing or bad ones).

        For a dataclass model: every field is a parameter of the same name, required unless it is
        one of ``optional_params`` (then the field's default applies when it is absent)."""
        cls._check_spec(spec)
        return cls(**cls._spec_arguments(spec))

    def to_spec(self) -> LightSpec:
        """The parameters to store in a capture; ``from_spec(to_spec())`` gives the same model.

        For a dataclass model: every field that is not None, in field order, arrays copied."""
        params: dict[str, Any] = {}
        for f in fields(self):  # type: ignore[arg-type]
            value = getattr(self, f.name)
            if value is not None:
                params[f.name] = value.copy() if isinstance(value, np.ndarray) else value
        return LightSpec(self.name, params)

    @abstractmethod
    def evaluate(self, t_us: np.ndarray, points_mm: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Unit direction towards the light and RGB intensity at times ``t_us`` (shape (T,)).

        Directional models return (T, 3) each, or (T, P, 3) read-only broadcasts when ``points_mm``
        (P, 3) is given; near models need ``points_mm`` and return (T, P, 3) each.
        """

    @classmethod
    def _check_spec(cls, spec: LightSpec) -> None:
        if spec.model != cls.name:
            raise UserError(f"light model {spec.model!r} given to the {cls.name!r} model")

    @classmethod
    def _spec_arguments(cls, spec: LightSpec) -> dict[str, Any]:
        """Constructor arguments from ``spec``, one per dataclass field in field order: a UserError
        names the first required parameter that is missing; an absent optional one is left out."""
        return {
            f.name: _param(spec, f.name)
            for f in fields(cls)  # type: ignore[arg-type]
            if f.name in spec.params or f.name not in cls.optional_params
        }


@dataclass(eq=False)
class RingLight(LightModel):
    """A directional light circling the optical axis at a fixed elevation above the image plane:
    φ(t) = phase_deg + sense·360°·(t − t0_us)/period_us, l(t) = (cos e cos φ, cos e sin φ, sin e)."""

    name: ClassVar[str] = "ring"
    summary: ClassVar[str] = "directional light circling the camera axis at constant elevation and speed"
    optional_params: ClassVar[tuple[str, ...]] = ("t0_us",)

    elevation_deg: float
    period_us: float
    phase_deg: float = 0.0
    sense: int = 1
    intensity: np.ndarray = field(default_factory=lambda: np.ones(3))
    t0_us: float = 0.0

    def __post_init__(self) -> None:
        self.elevation_deg = _scalar(self.name, "elevation_deg", self.elevation_deg)
        self.period_us = _positive(self.name, "period_us", self.period_us)
        self.phase_deg = _scalar(self.name, "phase_deg", self.phase_deg)
        self.sense = _sense(self.name, self.sense)
        self.intensity = _array(self.name, "intensity", self.intensity, (3,))
        self.t0_us = _scalar(self.name, "t0_us", self.t0_us)

    def angle_rad(self, t_us: np.ndarray) -> np.ndarray:
        """Azimuth φ(t) of the light, radians (not wrapped to one turn)."""
        return _ring_angle_rad(t_us, self.t0_us, self.period_us, self.phase_deg, self.sense)

    def evaluate(self, t_us: np.ndarray, points_mm: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        phi = self.angle_rad(t_us)
        e = np.deg2rad(self.elevation_deg)
        direction = np.stack(
            [np.cos(e) * np.cos(phi), np.cos(e) * np.sin(phi), np.full_like(phi, np.sin(e))], axis=-1
        )
        intensity = np.broadcast_to(self.intensity, direction.shape).copy()
        return _broadcast_directional(self.name, direction, intensity, points_mm)

    def integral(self, t0_us: np.ndarray | float, t1_us: np.ndarray | float) -> np.ndarray:
        """Closed form of ∫ l(t) dt from t0_us to t1_us with dt in seconds (direction only, no intensity);
        shape broadcast(t0_us, t1_us) + (3,)."""
        t0 = np.asarray(t0_us, dtype=np.float64)
        t1 = np.asarray(t1_us, dtype=np.float64)
        e = np.deg2rad(self.elevation_deg)
        omega = self.sense * 2.0 * np.pi / self.period_us  # rad per µs
        # φ(t1) is taken as φ(t0) plus the swept angle so that windows over a wrap integrate correctly.
        phi0 = self.angle_rad(t0)
        phi1 = phi0 + omega * (t1 - t0)
        x = np.cos(e) * (np.sin(phi1) - np.sin(phi0)) / omega
        y = -np.cos(e) * (np.cos(phi1) - np.cos(phi0)) / omega
        z = np.sin(e) * (t1 - t0) * np.ones_like(phi0)
        return np.stack([x, y, z], axis=-1) / US_PER_S


@dataclass(eq=False)
class SampledLight(LightModel):
    """Light directions and RGB intensities sampled at known times (e.g. the LEDs of a ring, or DiLiGenT
    lights in loop order). Between samples the direction is interpolated linearly and re-normalised and
    the intensity linearly; a periodic trajectory wraps modulo ``period_us`` (last sample → first sample
    + period), an aperiodic one holds its end samples."""

    name: ClassVar[str] = "sampled"
    summary: ClassVar[str] = "directions and RGB intensities at sample times, interpolated linearly and re-normalised"
    optional_params: ClassVar[tuple[str, ...]] = ("period_us",)

    times_us: np.ndarray
    directions: np.ndarray
    intensities: np.ndarray
    periodic: bool = False
    period_us: float | None = None

    def __post_init__(self) -> None:
        self.times_us = _array(self.name, "times_us", self.times_us, (-1,))
        self.directions = _array(self.name, "directions", self.directions, (-1, 3))
        self.intensities = _array(self.name, "intensities", self.intensities, (-1, 3))
        m = self.times_us.shape[0]
        if m == 0:
            raise UserError(f"light model {self.name!r}: needs at least one sample")
        if self.directions.shape[0] != m or self.intensities.shape[0] != m:
            raise UserError(f"light model {self.name!r}: times_us, directions and intensities differ in length")
        if np.any(np.diff(self.times_us) <= 0):
            raise UserError(f"light model {self.name!r}: sample times are not strictly increasing")
        if np.any(np.linalg.norm(self.directions, axis=-1) == 0):
            raise UserError(f"light model {self.name!r}: a direction is the zero vector")
        self.periodic = bool(self.periodic)
        if self.periodic:
            if self.period_us is None:
                raise UserError(f"light model {self.name!r}: a periodic trajectory needs 'period_us'")
            self.period_us = _positive(self.name, "period_us", self.period_us)
            if self.period_us <= self.times_us[-1] - self.times_us[0]:
                raise UserError(f"light model {self.name!r}: period_us {self.period_us:g} does not exceed the span of times_us")
        elif self.period_us is not None:
            raise UserError(f"light model {self.name!r}: period_us is given but the trajectory is not periodic")
        _, knots_d, _ = self._knots()
        unit_d = unit(knots_d)
        if np.any(np.sum(unit_d[:-1] * unit_d[1:], axis=-1) <= -1.0 + 1e-12):
            raise UserError(f"light model {self.name!r}: consecutive directions are opposite, the interpolation is undefined")

    @classmethod
    def _spec_arguments(cls, spec: LightSpec) -> dict[str, Any]:
        """The fields' arguments, after the sampled model's own rules: only the one interpolation, and
        ``periodic`` true or false."""
        interpolation = spec.params.get("interpolation", INTERPOLATION)
        if interpolation != INTERPOLATION:
            raise UserError(f"light model {spec.model!r}: interpolation {interpolation!r} is not supported (only {INTERPOLATION!r})")
        periodic = _param(spec, "periodic")
        if not isinstance(periodic, (bool, np.bool_)) and periodic not in (0, 1):
            raise UserError(f"light model {spec.model!r}: parameter 'periodic' must be true or false, got {periodic!r}")
        return {**super()._spec_arguments(spec), "periodic": bool(periodic)}

    def to_spec(self) -> LightSpec:
        params = super().to_spec().params
        # the format stores sample times as int64 µs (spec §8.2); the rule goes where files have always held
        # it, ahead of the optional period, so a capture's attributes are written in the same order
        params["times_us"] = np.round(self.times_us).astype(np.int64)
        period = params.pop("period_us", None)
        params["interpolation"] = INTERPOLATION
        if period is not None:
            params["period_us"] = period
        return LightSpec(self.name, params)

    def _knots(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Sample times, directions and intensities with the closing segment (periodic) or a copy of the
        only sample (one sample, aperiodic) appended, so every time falls into a segment."""
        t, d, e = self.times_us, self.directions, self.intensities
        if self.periodic:
            assert self.period_us is not None
            return np.append(t, t[0] + self.period_us), np.vstack([d, d[:1]]), np.vstack([e, e[:1]])
        if t.shape[0] == 1:
            return np.append(t, t[0] + 1.0), np.vstack([d, d]), np.vstack([e, e])
        return t, d, e

    def evaluate(self, t_us: np.ndarray, points_mm: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        knots_t, knots_d, knots_e = self._knots()
        t = np.asarray(t_us, dtype=np.float64)
        if self.periodic:
            assert self.period_us is not None
            t = knots_t[0] + np.mod(t - knots_t[0], self.period_us)
        else:
            t = np.clip(t, knots_t[0], knots_t[-1])
        i = np.clip(np.searchsorted(knots_t, t, side="right") - 1, 0, knots_t.shape[0] - 2)
        w = ((t - knots_t[i]) / (knots_t[i + 1] - knots_t[i]))[..., None]
        direction = unit((1.0 - w) * knots_d[i] + w * knots_d[i + 1])
        intensity = (1.0 - w) * knots_e[i] + w * knots_e[i + 1]
        return _broadcast_directional(self.name, direction, intensity, points_mm)


def pixel_points_mm(
    height: int,
    width: int,
    pixel_pitch_mm: float,
    center_px: tuple[float, float] | np.ndarray | None = None,
    depth_mm: float | np.ndarray | None = None,
) -> np.ndarray:
    """Surface points of an orthographic image in mm, (H·W, 3) in row-major pixel order:
    X(u, v) = ((u − cx)·pitch, (cy − v)·pitch, depth or 0), default (cx, cy) = ((W−1)/2, (H−1)/2).
    ``depth_mm`` is a scalar or an (H, W) map of z (towards the camera)."""
    cx, cy = ((width - 1) / 2.0, (height - 1) / 2.0) if center_px is None else (float(center_px[0]), float(center_px[1]))
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    z = np.zeros((height, width)) if depth_mm is None else np.broadcast_to(np.asarray(depth_mm, dtype=np.float64), (height, width))
    return np.stack([(u - cx) * pixel_pitch_mm, (cy - v) * pixel_pitch_mm, z], axis=-1).reshape(-1, 3)


@dataclass(eq=False)
class NearRingLight(LightModel):
    """A point light on a ring of ``radius_mm`` at ``height_mm`` above the plane z = 0, moving like
    ``ring``: P(t) = (R cos φ, R sin φ, h). At a surface point X the direction is normalize(P − X) and
    the intensity falls off with the inverse square, scaled to equal ``intensity`` at the ring centre:
    intensity·(R² + h²)/|P − X|²."""

    name: ClassVar[str] = "near-ring"
    summary: ClassVar[str] = "point light circling on a ring of given radius and height, inverse-square fall-off"
    near: ClassVar[bool] = True
    optional_params: ClassVar[tuple[str, ...]] = ("t0_us", "center_px")

    radius_mm: float
    height_mm: float
    pixel_pitch_mm: float
    period_us: float
    phase_deg: float = 0.0
    sense: int = 1
    intensity: np.ndarray = field(default_factory=lambda: np.ones(3))
    t0_us: float = 0.0
    center_px: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.radius_mm = _positive(self.name, "radius_mm", self.radius_mm)
        self.height_mm = _positive(self.name, "height_mm", self.height_mm)
        self.pixel_pitch_mm = _positive(self.name, "pixel_pitch_mm", self.pixel_pitch_mm)
        self.period_us = _positive(self.name, "period_us", self.period_us)
        self.phase_deg = _scalar(self.name, "phase_deg", self.phase_deg)
        self.sense = _sense(self.name, self.sense)
        self.intensity = _array(self.name, "intensity", self.intensity, (3,))
        self.t0_us = _scalar(self.name, "t0_us", self.t0_us)
        if self.center_px is not None:
            self.center_px = _array(self.name, "center_px", self.center_px, (2,))

    def pixel_points(self, height: int, width: int, depth_mm: float | np.ndarray | None = None) -> np.ndarray:
        """Surface points (H·W, 3) in mm of an image of this rig's pixel pitch and centre."""
        return pixel_points_mm(height, width, self.pixel_pitch_mm, self.center_px, depth_mm)

    def position_mm(self, t_us: np.ndarray) -> np.ndarray:
        """Light position P(t), shape t.shape + (3,)."""
        phi = _ring_angle_rad(t_us, self.t0_us, self.period_us, self.phase_deg, self.sense)
        r = self.radius_mm
        return np.stack([r * np.cos(phi), r * np.sin(phi), np.full_like(phi, self.height_mm)], axis=-1)

    def evaluate(self, t_us: np.ndarray, points_mm: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        points = _points(self.name, points_mm)
        offset = self.position_mm(t_us)[..., None, :] - points
        dist2 = np.sum(offset * offset, axis=-1, keepdims=True)
        direction = offset / np.sqrt(dist2)
        intensity = self.intensity * ((self.radius_mm**2 + self.height_mm**2) / dist2)
        return direction, intensity


def build_light_model(spec: LightSpec) -> LightModel:
    """The light model a capture stores, looked up by name in the plugin registry (so plugins' models
    work as well as the built-in ones)."""
    from pstoolkit.plugin.manager import get_registries

    cls = get_registries().light_models.get(spec.model).obj
    return cls.from_spec(spec)
