"""The ``dualres`` solver: DualResPS (frames + events) by neural inverse rendering.

Pipeline: ``preprocess`` (cast shadows from events, importance-sampled frame times, event pairs with
refractory compensation and confidence, closed-form initialisation) → ``train.build_problem`` →
Adam on the frame, event and TV losses (eq. 24–26) → maps.

Presets:

- ``paper``: the paper's coordinate MLP (``model.NeuralField``: positional encoding, 8 × 256, skip at
  layer 4, normal head, material head 1 + 4 × 128) trained from scratch for 1200 epochs on the
  per-pixel importance samples of eq. 21/23, λ_e = 0.05. An epoch is, as in LL22a, a pass over the
  data in mini-batches: spatial tiles of 8 × 8 frame pixels, shuffled (and the tiling offset at
  random) every epoch, about 512 pixels per Adam step, each step fitting its pixels' three frames,
  the event pairs of its super pixels and the TV pairs inside it; Adam at 1e-3 decaying
  exponentially to 1e-4. Simulated GGX scenes at 64 px (one CPU thread): sphere 0.64°, blobs
  1.27°, relief 0.23° after 1200 epochs (0.35–0.65 s each); one full-batch step per epoch had not
  converged after 100 epochs (6–16°). The MLP runs on every pixel every epoch: at 256 px an epoch
  (128 steps) takes about 9.4 s, so the 1200 epochs take about 3 h on this CPU.
- ``fast`` (default): ``model.GridField`` — per-pixel normal and albedo at frame resolution started from
  the closed-form initialisation (the three equivalent lights of eq. 14/16, Table 1 for the rest),
  materials on a grid at event resolution (the low-frequency unknowns of the paper's DoF analysis),
  TV warm-up for smoothness, 150 full-batch epochs on 8 samples per frame of a time grid shared by
  all pixels (broadcast pixels × samples, no gather or scatter), λ_e = 4: per-pixel unknowns have
  no network to share information between pixels, so the events must weigh more (at 128 px,
  relief 1.93° → 1.22°, sphere 0.82° → 0.67°, blobs 1.44° → 1.11° from λ_e = 0.05 to 4), and the
  specular materials need the epochs (relief 1.22° at 50, 0.82° at 150). No network is evaluated,
  so an epoch costs the rendering alone. At 64 px: sphere 0.63°, blobs 1.09°, relief 0.78° in
  about 6 s per scene, on average 0.12° behind ``paper`` at about 1/100 of its time; ``paper``
  stays ahead on the low-contrast relief (0.23°), where its network shares information between
  pixels that per-pixel unknowns do not.

Outputs: ``normal``; maps ``albedo`` (diffuse ρ_d), ``f0``, ``roughness``, ``metallic`` and
``base_color`` (derived for PBR workflows, supplement §4.2; the specular model's own maps for
``sg``/``mlp``), and ``cast_shadow`` (the share of each pixel's exposure time the cast-shadow mask
removed). Albedo and F0 are in frame units per unit light per second (the exposure gain folded in);
metallic and base colour are computed on albedo and F0 relative to the capture's albedo scale.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
import torch

import psfmt
from pstoolkit import Option, Solver, SolverResult
from pstoolkit.solver import Progress
from pstoolkit_dualres.preprocess import SCALE_RULES, PreprocessOptions, preprocess
from pstoolkit_dualres.render import REFLECTANCES, pbr_from_specular
from pstoolkit_dualres.train import TrainConfig, build_field, build_problem, train

PRESETS: dict[str, dict[str, Any]] = {
    "fast": {"epochs": 150, "lr": 5e-3, "material_lr": 5e-2, "event_weight": 4.0, "tv_weight": 0.02, "frame_samples": 8,
             "batch_pixels": 0},
    "paper": {"epochs": 1200, "lr": 1e-3, "material_lr": 1e-3, "event_weight": 0.05, "tv_weight": 0.02, "frame_samples": 0,
              "batch_pixels": 512},
}
SCALED_MAPS = frozenset({"albedo", "f0", "specular_tint"})


@contextmanager
def deterministic(warn_only: bool) -> Iterator[None]:
    """Torch's deterministic kernels for the duration (the scatter-adds of gathers' gradients are not,
    by default, on several threads); on CUDA a kernel without a deterministic variant only warns."""
    enabled, warn = torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled()
    torch.use_deterministic_algorithms(True, warn_only=warn_only)
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(enabled, warn_only=warn)


def _config(options: dict[str, Any]) -> TrainConfig:
    preset = PRESETS[options["preset"]]

    def pick(name: str) -> Any:
        return options[name] if options[name] > 0 else preset[name]

    return TrainConfig(
        preset=options["preset"], epochs=options["epochs"] if options["epochs"] >= 0 else preset["epochs"], lr=pick("lr"), material_lr=pick("material_lr"),
        frame_weight=options["frame_weight"],
        event_weight=options["event_weight"] if options["event_weight"] >= 0 else preset["event_weight"],
        tv_weight=options["tv_weight"] if options["tv_weight"] >= 0 else preset["tv_weight"],
        tv_fraction=options["tv_fraction"], event_batch=options["event_batch"], seed=options["seed"],
        frame_samples=options["frame_samples"] if options["frame_samples"] >= 0 else preset["frame_samples"],
        batch_pixels=options["batch_pixels"] if options["batch_pixels"] >= 0 else preset["batch_pixels"],
    )


class DualRes(Solver):
    name = "dualres"
    summary = "DualResPS: three long-exposure frames + events, neural inverse rendering (torch)"
    options = (
        Option("preset", str, "fast", "fast (grid design, closed-form start) or paper (the paper's MLP, 1200 epochs)",
               choices=tuple(PRESETS)),
        Option("epochs", int, -1, "Adam epochs; 0 returns the closed-form initialisation (−1 = the preset's: fast 150, paper 1200)",
               minimum=-1),
        Option("seed", int, 0, "seed of the network initialisation and the event batches"),
        Option("specular", str, "ggx", "specular model: ggx, sg (spherical Gaussians), mlp (LL22a bases), metallic",
               choices=tuple(REFLECTANCES)),
        Option("shadows", bool, True, "use the cast-shadow mask from events (false: the ablation without it)"),
        Option("lr", float, 0.0, "learning rate of normals/albedo or the network (0 = the preset's)", minimum=0.0),
        Option("material_lr", float, 0.0, "learning rate of the material grid (0 = the preset's)", minimum=0.0),
        Option("frame_weight", float, 1.0, "λ_f, weight of the frame loss (eq. 24)", minimum=0.0),
        Option("event_weight", float, -1.0, "λ_e, weight of the event loss (eq. 25) (−1 = the preset's: fast 4, paper 0.05)",
               minimum=-1.0),
        Option("tv_weight", float, -1.0, "λ_tv, weight of the TV warm-up (−1 = the preset's)"),
        Option("tv_fraction", float, 0.3, "share of the epochs over which the TV term fades to zero", minimum=0.0, maximum=1.0),
        Option("event_batch", int, 16384, "event pairs drawn per epoch (0 = all)", minimum=0),
        Option("frame_samples", int, -1,
               "samples per frame on a time grid shared by all pixels; 0 = the per-pixel importance samples of "
               "preprocessing (−1 = the preset's: fast 8, paper 0)", minimum=-1),
        Option("batch_pixels", int, -1,
               "frame pixels per mini-batch, an epoch being a pass over all pixels; 0 = one full-batch step per "
               "epoch (−1 = the preset's: fast 0, paper 512)", minimum=-1),
        Option("scale_rule", str, "windows",
               "where the irradiance scale s may change: windows (exposure-window bounds) or spikes (the strongest "
               "event bursts, at most three values per turn, as in the paper)", choices=SCALE_RULES),
    )
    needs = frozenset({"frames", "events", "lights"})

    def solve(self, capture: psfmt.Capture, options: dict[str, Any], progress: Progress) -> SolverResult:
        torch.manual_seed(options["seed"])
        config = _config(options)
        started = time.perf_counter()
        progress(0.0, "preprocessing")
        pre = preprocess(capture, PreprocessOptions(use_shadows=options["shadows"], scale_rule=options["scale_rule"]),
                         lambda fraction, message: progress(0.1 * fraction, message))
        problem = build_problem(pre, capture.calibration.view_direction, shadows=options["shadows"], device=self.device,
                                frame_samples=config.frame_samples)
        seconds_pre = time.perf_counter() - started
        with deterministic(warn_only=str(self.device) != "cpu"):
            reflectance = REFLECTANCES[options["specular"]]().to(self.device)
            field = build_field(problem, reflectance, config.preset)
            history = train(problem, field, reflectance, config, lambda fraction, message: progress(0.1 + 0.9 * fraction, message))
            with torch.no_grad():
                normal, albedo, raw = field()
                maps = {name: value.cpu().numpy() for name, value in reflectance.maps(albedo, raw).items()}
                normal = normal.cpu().numpy()
        return self._result(problem, normal, maps, options, {
            **problem.diagnostics, "preset": config.preset, "epochs": config.epochs,
            "preprocess_seconds": seconds_pre, "final_loss": history[-1] if history else None,
            "device": str(self.device), "preprocess": pre.diagnostics,
        })

    @staticmethod
    def _result(problem: Any, normal: np.ndarray, maps: dict[str, np.ndarray], options: dict[str, Any],
                diagnostics: dict[str, Any]) -> SolverResult:
        h, w, pixels = problem.height, problem.width, problem.pixels

        def full(values: np.ndarray) -> np.ndarray:
            out = np.zeros((h * w,) + values.shape[1:], dtype=np.float32)
            out[pixels] = values
            return out.reshape((h, w) + values.shape[1:])

        # Reflectance maps leave the model in units of the albedo scale; metallic and the base colour
        # derived from ρ_d and F0 are computed on those relative values (reflectances in [0, 1]).
        out = {name: full(value * problem.albedo_scale if name in SCALED_MAPS else value) for name, value in maps.items()}
        if options["specular"] == "ggx":
            metallic, base = pbr_from_specular(maps["albedo"], maps["f0"])
            out.update(metallic=full(metallic), base_color=full(base))
        out["cast_shadow"] = problem.shadow_fraction.astype(np.float32)
        mask = np.zeros(h * w, dtype=bool)
        mask[pixels] = True
        return SolverResult(normal=full(normal), mask=mask.reshape(h, w), maps=out, diagnostics=diagnostics)
