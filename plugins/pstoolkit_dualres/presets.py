"""Named configurations of the ``dualres`` solver (``--set preset=NAME``), each a complete record of
what a run does; single options override a preset's value.

- ``fast`` (default): ``fields.PyramidField`` started from the closed form, 150 full-batch epochs on
  8 samples per frame of a time grid shared by all pixels, a strong event loss (λ_e = 8: the pyramid
  shares information between pixels far less than a network, so the events must weigh more), and a
  surface-based shadow detector run again after the first 40 % of the epochs, the fit carrying on
  under the new mask from where it is.
- ``paper``: the paper's coordinate MLP (``fields.NeuralField``, facing the camera with the closed
  form's median albedo at the start) trained for 1200 epochs on the importance samples of eq. 21/23 in
  mini-batches of 512 pixels (8 × 8 tiles), Adam at 1e-3 decaying to 1e-4 (as LL22a trains), λ_e = 8 as
  ``fast`` (the paper gives no weight: the events are what pin the specular lobe its three frames cannot,
  main §3.2, and a weak event term leaves the network's roughness where its start takes it); a
  surface-based detector runs again after a quarter and after half of the epochs.

A run records the preset it used, overrides applied (``resolve``), under ``preset`` in its
diagnostics (``Preset.record``), which ``result.json`` carries.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from typing import Any

FIELDS = ("pyramid", "mlp")


@dataclass(frozen=True)
class Preset:
    """``field`` (pyramid or mlp), ``epochs``, learning rates of the surface and the smooth materials,
    λ_e, λ_tv with its fading share, ``frame_samples`` per frame on a shared grid (0: the importance
    samples), ``batch_pixels`` (0: full batches), ``smoothness`` of the pyramid's finer levels, and
    ``detect_at``: shares of the epochs after which a detector that uses the surface runs again."""

    name: str
    field: str
    epochs: int
    lr: float
    material_lr: float
    event_weight: float
    tv_weight: float
    tv_fraction: float
    frame_samples: int
    batch_pixels: int
    smoothness: float
    detect_at: tuple[float, ...]

    def record(self) -> dict[str, Any]:
        """Every field by name, as JSON writes it (``detect_at`` a list), for a run's diagnostics."""
        return {**asdict(self), "detect_at": list(self.detect_at)}


PRESETS: dict[str, Preset] = {
    "fast": Preset("fast", field="pyramid", epochs=150, lr=5e-3, material_lr=5e-2, event_weight=8.0, tv_weight=0.05,
                   tv_fraction=0.3, frame_samples=8, batch_pixels=0, smoothness=3.0, detect_at=(0.4,)),
    "paper": Preset("paper", field="mlp", epochs=1200, lr=1e-3, material_lr=1e-3, event_weight=8.0, tv_weight=0.02,
                    tv_fraction=0.3, frame_samples=0, batch_pixels=512, smoothness=0.0, detect_at=(0.25, 0.5)),
}

OVERRIDES = ("epochs", "lr", "material_lr", "event_weight", "tv_weight", "tv_fraction", "frame_samples",
             "batch_pixels", "smoothness")
"""Solver options that replace a preset's value when set (a negative value keeps the preset's)."""


def resolve(options: dict[str, Any]) -> Preset:
    """The preset named by ``options["preset"]`` with every set override applied."""
    preset = PRESETS[options["preset"]]
    changes = {name: options[name] for name in OVERRIDES if options[name] >= 0}
    return replace(preset, **changes)
