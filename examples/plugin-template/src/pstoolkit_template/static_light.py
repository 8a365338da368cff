"""The ``static`` light model: one directional light that does not move (a single fixed LED far away)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from psfmt import LightSpec
from pstoolkit import LightModel, UserError


def _vector3(key: str, value: object) -> np.ndarray:
    array = np.asarray(value, dtype=np.float64)
    if array.shape != (3,) or not np.all(np.isfinite(array)):
        raise UserError(f"light model 'static': parameter {key!r} must be 3 finite numbers, got {value!r}")
    return array


@dataclass(eq=False)
class StaticLight(LightModel):
    """Direction (unit, camera frame, towards the light) and RGB intensity, the same at all times."""

    name = "static"
    summary = "one fixed directional light (unit direction and RGB intensity)"
    period_us = None

    direction: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    intensity: np.ndarray = field(default_factory=lambda: np.ones(3))

    def __post_init__(self) -> None:
        direction = _vector3("direction", self.direction)
        length = np.linalg.norm(direction)
        if length == 0:
            raise UserError("light model 'static': parameter 'direction' is the zero vector")
        self.direction = direction / length
        self.intensity = _vector3("intensity", self.intensity)

    @classmethod
    def from_spec(cls, spec: LightSpec) -> StaticLight:
        cls._check_spec(spec)
        if "direction" not in spec.params:
            raise UserError("light model 'static': parameter 'direction' is missing")
        return cls(direction=spec.params["direction"], intensity=spec.params.get("intensity", np.ones(3)))

    def to_spec(self) -> LightSpec:
        return LightSpec(self.name, {"direction": self.direction.copy(), "intensity": self.intensity.copy()})

    def evaluate(self, t_us: np.ndarray, points_mm: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        shape = np.shape(t_us) + (() if points_mm is None else (len(points_mm),)) + (3,)
        return np.broadcast_to(self.direction, shape).copy(), np.broadcast_to(self.intensity, shape).copy()
