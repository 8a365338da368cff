"""Light calibrations: the ``light calibrations`` registry's kind, what one returns, and where it goes.

A light calibration measures a rig's light model from a recording of a calibration target (a chrome
sphere under the lights, say) and returns a ``LightFit``: the model (a ``psfmt.LightSpec`` any
``--lights FILE`` or capture takes), the directions and intensities it measured (one per light, or
per time window of a moving light) and how well the model fits them. ``pstoolkit calibrate lights``
writes the fit as a DiLiGenT-style light folder (``write_light_folder``) and stores the model in
captures (``store_lights``).

    fit = get_registries().light_calibrations.get("sphere-frames").obj().calibrate(Path("ball/"), **options)
"""

from __future__ import annotations

import json
import os
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

import psfmt
from pstoolkit.io.diligent_layout import DIRECTIONS, INTENSITIES
from pstoolkit.plugin.options import Option

LIGHTS_JSON = "lights.json"
"""The light model of a calibration folder, ``{"model": NAME, "params": {…}}`` (``convert … --lights``)."""


@dataclass
class LightFit:
    """A measured light model. ``spec`` is the model; ``directions`` (K, 3) unit vectors (camera
    frame: x right, y up, z towards the camera) and ``intensities`` (K, 3) RGB are what was measured,
    at ``times_us`` (K,) on the model's clock (light k of a discrete set at k µs); ``residual_deg``
    is the RMS angle between the measured directions and the model's (None where the model is the
    measurements themselves); ``details`` holds the method's own figures (JSON-ready scalars)."""

    spec: psfmt.LightSpec
    directions: np.ndarray
    intensities: np.ndarray
    times_us: np.ndarray
    residual_deg: float | None = None
    details: dict[str, Any] = field(default_factory=dict)


class LightCalibration(ABC):
    """A way to measure a light model: an entry of the ``light calibrations`` registry
    (``pstoolkit calibrate lights SOURCE --method NAME``). Subclasses set ``name``, ``summary`` and
    ``options`` (typed, given as ``--set key=value``) and implement ``calibrate``; ``accepts`` says
    whether the method is the natural one for a source, so the command can pick it."""

    name: ClassVar[str]
    summary: ClassVar[str]
    options: ClassVar[tuple[Option, ...]] = ()

    @classmethod
    def accepts(cls, source: Path) -> bool:
        """Whether ``source`` is what this method measures from (used to choose a default method)."""
        return False

    @abstractmethod
    def calibrate(self, source: Path, **options: Any) -> LightFit:
        """Measure the lights from ``source`` (a file or folder); ``options`` are the entry's options
        by name, defaults filled in. UserError names the file and the problem."""


def spec_json(spec: psfmt.LightSpec) -> dict[str, Any]:
    """``{"model": NAME, "params": {…}}`` with arrays as lists: the file ``--lights`` reads."""
    params = {k: (v.tolist() if isinstance(v, np.ndarray) else v.item() if isinstance(v, np.generic) else v) for k, v in spec.params.items()}
    return {"model": spec.model, "params": params}


def _write_text(path: Path, text: str) -> None:
    path.write_text(text, encoding="utf-8")


def write_light_folder(out: Path, fit: LightFit, report: dict[str, Any]) -> None:
    """Write ``light_directions.txt`` (K lines ``x y z``), ``light_intensities.txt`` (K lines
    ``r g b``), ``lights.json`` (the model) and ``calibration.json`` (``report``) into the folder
    ``out`` as a unit (``pstoolkit.io.folders.atomic_folder``): a folder of that name is replaced
    only once the new one is complete."""
    from pstoolkit.io.folders import atomic_folder

    with atomic_folder(out) as folder:
        _write_text(folder / DIRECTIONS, "".join(f"{x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in fit.directions))
        _write_text(folder / INTENSITIES, "".join(f"{r:.6f} {g:.6f} {b:.6f}\n" for r, g, b in fit.intensities))
        _write_text(folder / LIGHTS_JSON, json.dumps(spec_json(fit.spec), indent=2) + "\n")
        _write_text(folder / "calibration.json", json.dumps(report, indent=2) + "\n")


PERIOD_TOLERANCE = 0.01
"""A fitted period within this fraction of a capture's own gives way to it (``keep_period``)."""


def keep_period(spec: psfmt.LightSpec, current: psfmt.LightSpec | None) -> psfmt.LightSpec:
    """``spec`` with the period of ``current`` (a capture's light model) when both state one and they
    agree within ``PERIOD_TOLERANCE``: a capture's frames are timed by the light's own period pulses,
    and a fitted period (good to about 0.1 %) must not contradict them."""
    if current is None or "period_us" not in spec.params or "period_us" not in current.params:
        return spec
    try:
        fitted, own = float(spec.params["period_us"]), float(current.params["period_us"])
    except (TypeError, ValueError):
        return spec
    if not (own > 0 and abs(fitted / own - 1.0) <= PERIOD_TOLERANCE):
        return spec
    return psfmt.LightSpec(spec.model, {**spec.params, "period_us": own})


def store_lights(path: str | os.PathLike[str], fit: LightFit) -> None:
    """Set the light model of the capture at ``path`` to ``fit.spec``, rewriting it atomically
    (everything else kept); the capture's own period is kept where it agrees (``keep_period``). A
    classic capture whose frames carry one light each, as many as the fit measured, gets the
    measured directions and intensities on its frames too."""
    capture = psfmt.read(path)
    try:
        capture.lights = keep_period(fit.spec, capture.lights)
        frames = capture.frames
        if frames is not None and frames.light_direction is not None and frames.count == len(fit.directions):
            frames.light_direction = np.asarray(fit.directions, dtype=np.float64)
            frames.light_intensity = np.asarray(fit.intensities, dtype=np.float64)
        psfmt.write(capture, path)
    finally:
        capture.close()
