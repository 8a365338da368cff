"""The ``frameps`` solver: Woodham's least-squares photometric stereo on frames with known lights.

Lights: instantaneous ones (direction × RGB intensity) for classic captures, equivalent lights
(∫ e_c(t) l(t) dt over each exposure window, from the capture's light model) for long exposures.

Colour: the normal is solved once per pixel on grey, then the RGB albedo is fitted per channel by
projecting each channel onto the grey solution's shading. One normal per pixel is what the
surface has; the grey mixes the three channels' photons (more SNR than any one), whereas three
per-channel solves would give three normals that disagree under noise. Each frame's channel c is
first divided by the strength |L_kc| of its light (DiLiGenT's "divide by the light intensities"),
so the grey is g_k = Σ_c w_c A_kc / |L_kc| with Rec. 601 weights w, and its light the same mix of
the unit channel lights. For a white light this is exactly Woodham on the grey image.

With the defaults (all frames, robust off) this is the plain least squares of the literature: every
observation of every pixel, shadows and highlights included, no threshold on dark values.
``robust=true`` drops, per pixel, the darkest ``dark_fraction`` of the observations (attached and
cast shadows) and every saturated one, and keeps all of a pixel's observations when fewer than three
would be left (such pixels are counted in ``diagnostics["fallback_pixels"]``).

Mask: a pixel is in when its brightest observation (any channel, any frame used) exceeds
``threshold`` of saturation and its normal equations are well conditioned (≥ 3 observations whose
lights are not coplanar). Albedo is in frame units per unit light (relative: the exposure gain is
unknown).

Runs in numpy on the CPU whatever ``--device`` says: the work is a few matrix products.
"""

from __future__ import annotations

from typing import Any

import numpy as np

import psfmt
from pstoolkit import Option, Progress, Solver, SolverResult, UserError
from pstoolkit_frameps.leastsq import MIN_OBSERVATIONS, robust_weights, solve_shading
from pstoolkit_frameps.lights import (
    channel_weights,
    frame_lights,
    spread,
    trajectory_order,
)


def _unit_lights(lights: np.ndarray, where: str) -> tuple[np.ndarray, np.ndarray]:
    """Each (frame, channel) light (K, C, 3) split into its strength (K, C) and unit direction."""
    strength = np.linalg.norm(lights, axis=-1)
    dark = np.argwhere(strength <= 0)
    if dark.size:
        k, c = dark[0]
        raise UserError(f"frameps: {where}: frame {k} has no light in channel {c}")
    return strength, lights / strength[..., None]


class FramePS(Solver):
    name = "frameps"
    summary = "least-squares photometric stereo on frames with known or equivalent lights (numpy, CPU)"
    options = (
        Option("frames", int, 0, "use this many frames spread evenly over the trajectory (0 = all)", minimum=0),
        Option("robust", bool, False, "drop each pixel's darkest and saturated observations before solving"),
        Option(
            "dark_fraction", float, 0.25,
            "robust: share of each pixel's observations dropped as shadowed (the darkest)", minimum=0.0, maximum=0.9,
        ),
        Option(
            "saturation_level", float, 1.0,
            "robust: an observation with any channel at or above this fraction of saturation is dropped",
            minimum=0.0, maximum=1.0,
        ),
        Option(
            "threshold", float, 0.002,
            "mask: a pixel is in when its brightest observation exceeds this fraction of saturation",
            minimum=0.0, maximum=1.0,
        ),
    )
    needs = frozenset({"frames"})
    robust_options = ("dark_fraction", "saturation_level")
    """Options that only the robust selection reads."""

    @classmethod
    def resolve_options(cls, options: dict[str, Any]) -> dict[str, Any]:
        """The options as given (none is a placeholder: ``frames=0`` means every frame, whatever the
        capture holds); UserError for a robust-selection option changed while ``robust`` is off, where
        nothing would read it."""
        if not options["robust"]:
            changed = [o for o in cls.options if o.name in cls.robust_options and options[o.name] != o.default]
            if changed:
                given = ", ".join(f"{o.name}={options[o.name]:g}" for o in changed)
                raise UserError(f"frameps: option {given} cannot apply: only robust=true drops observations (set robust=true, or leave it out)")
        return options

    @staticmethod
    def _check_robust(options: dict[str, Any], frames: int, where: str) -> None:
        """UserError when robust selection cannot drop anything from ``frames`` observations per pixel:
        least squares needs ``MIN_OBSERVATIONS`` (3) of them, and a pixel left with fewer falls back to
        all of its observations (``leastsq.robust_weights``), so robust=true needs more than 3 frames,
        and a ``dark_fraction`` above 0 must drop at least one frame and leave at least 3."""
        if frames <= MIN_OBSERVATIONS:
            raise UserError(
                f"frameps: option robust=true needs more than {MIN_OBSERVATIONS} frames, {where} gives {frames}: "
                f"least squares needs {MIN_OBSERVATIONS} observations per pixel, so none can be dropped"
            )
        fraction = options["dark_fraction"]
        drop = int(np.floor(fraction * frames))
        if fraction > 0 and drop == 0:
            raise UserError(
                f"frameps: option dark_fraction={fraction:g} drops none of the {frames} frames of {where} "
                f"(the darkest {fraction:g} × {frames} rounds down to 0; use at least {1 / frames:.3g})"
            )
        if frames - drop < MIN_OBSERVATIONS:
            raise UserError(
                f"frameps: option dark_fraction={fraction:g} drops {drop} of the {frames} frames of {where}, leaving fewer "
                f"than the {MIN_OBSERVATIONS} least squares needs, so every pixel would keep all of them"
            )

    def solve(self, capture: psfmt.Capture, options: dict[str, Any], progress: Progress) -> SolverResult:
        frames = capture.frames
        assert frames is not None
        where = str(capture.path or "the capture")
        if options["frames"] > frames.count:
            raise UserError(f"frameps: option frames={options['frames']} exceeds the {frames.count} frames of {where}")
        indices = spread(trajectory_order(frames, where), options["frames"])
        if len(indices) < 3:
            raise UserError(f"frameps: {where}: least squares needs at least 3 frames, got {len(indices)}")
        if options["robust"]:
            self._check_robust(options, len(indices), where)
        lights, kind = frame_lights(capture, indices)
        strength, unit = _unit_lights(lights, where)
        weights_c = channel_weights(frames.channels)
        grey_lights = np.einsum("c,kcx->kx", weights_c, unit)

        h, w = frames.height, frames.width
        k_used = len(indices)
        grey = np.empty((k_used, h * w), dtype=np.float32)
        saturated = np.zeros((k_used, h * w), dtype=bool)
        peak = np.zeros(h * w, dtype=np.float32)
        for i, k in enumerate(indices):
            image = frames.as_float(int(k)).reshape(h * w, -1)
            grey[i] = image @ (weights_c / strength[i]).astype(np.float32)
            brightest = image.max(axis=1)
            saturated[i] = brightest >= options["saturation_level"]
            np.maximum(peak, brightest, out=peak)
            progress(0.5 * (i + 1) / k_used, "frames")

        if options["robust"]:
            weights, fallback = robust_weights(grey, saturated, options["dark_fraction"])
        else:
            weights, fallback = np.ones_like(saturated), np.zeros(h * w, dtype=bool)
        b, ok = solve_shading(grey, grey_lights, weights)
        length = np.linalg.norm(b, axis=1)
        mask = ok & (length > 0) & (peak > options["threshold"])
        normal = np.zeros((h * w, 3))
        normal[mask] = b[mask] / length[mask, None]
        progress(0.6, "solved")

        albedo = self._albedo(frames, indices, strength, unit, normal, weights, mask, progress)
        diagnostics = {
            "lights": kind,
            "frames_used": [int(k) for k in indices],
            "n_frames": k_used,
            "robust": bool(options["robust"]),
            "fallback_pixels": int(np.count_nonzero(fallback & mask)),
            "mask_pixels": int(np.count_nonzero(mask)),
            "grey_weights": [float(x) for x in weights_c],
        }
        return SolverResult(
            normal=normal.reshape(h, w, 3),
            mask=mask.reshape(h, w),
            maps={"albedo": albedo.reshape(h, w, -1).astype(np.float32)},
            diagnostics=diagnostics,
            frames_used=k_used,
        )

    @staticmethod
    def _albedo(
        frames: psfmt.Frames,
        indices: np.ndarray,
        strength: np.ndarray,
        unit: np.ndarray,
        normal: np.ndarray,
        weights: np.ndarray,
        mask: np.ndarray,
        progress: Progress,
    ) -> np.ndarray:
        """Per-channel albedo ρ_c = Σ A_kc s_kc / Σ s_kc² with shading s_kc = L̂_kc·n over the lit
        observations the normal was solved from; a second pass over the frames keeps memory at one
        grey stack."""
        h, w = frames.height, frames.width
        numerator = np.zeros((h * w, frames.channels))
        denominator = np.zeros((h * w, frames.channels))
        for i, k in enumerate(indices):
            image = frames.as_float(int(k)).reshape(h * w, -1) / strength[i]
            shading = normal @ unit[i].T
            use = weights[i][:, None] & (shading > 0)
            numerator += np.where(use, image * shading, 0.0)
            denominator += np.where(use, shading * shading, 0.0)
            progress(0.6 + 0.4 * (i + 1) / len(indices), "albedo")
        albedo = np.divide(numerator, denominator, out=np.zeros_like(numerator), where=denominator > 0)
        albedo[~mask] = 0.0
        return albedo
