"""The light each frame saw, per colour channel, and the order frames follow along the trajectory."""

from __future__ import annotations

import numpy as np

import psfmt
from pstoolkit import GREY_WEIGHTS, UserError, build_light_model
from pstoolkit.optics.equivalent import equivalent_lights


def channel_weights(channels: int) -> np.ndarray:
    """Weights that turn ``channels`` colour channels into grey (RGB → luma, one channel → itself)."""
    if channels == 3:
        return np.asarray(GREY_WEIGHTS)
    if channels == 1:
        return np.ones(1)
    raise UserError(f"frameps: frames with {channels} channels are not supported (expected 1 or 3)")


def trajectory_order(frames: psfmt.Frames, where: str) -> np.ndarray:
    """Frame indices in trajectory order: by exposure start for long exposures, by light azimuth
    for instantaneous lights (the order round a ring, whatever order the frames are stored in)."""
    if frames.has_instant_lights:
        d = frames.light_direction
    elif frames.has_windows:
        return np.argsort(frames.t_start_us, kind="stable")
    else:
        raise UserError(f"frameps: {where} gives its frames neither light directions nor exposure windows")
    return np.argsort(np.arctan2(d[:, 1], d[:, 0]), kind="stable")


def spread(order: np.ndarray, count: int) -> np.ndarray:
    """``count`` entries of ``order`` evenly spaced along it (all of it for ``count`` 0)."""
    if count == 0 or count == len(order):
        return order
    return order[(np.arange(count) * len(order)) // count]


def frame_lights(capture: psfmt.Capture, indices: np.ndarray) -> tuple[np.ndarray, str]:
    """Light vectors (K, C, 3) of the frames ``indices`` per channel (direction × intensity, or the
    equivalent light ∫ e_c(t) l(t) dt of the exposure window) and which kind they are; the frames
    have one or the other (``trajectory_order`` checked)."""
    frames = capture.frames
    assert frames is not None
    channels = frames.channels
    if frames.has_instant_lights:
        direction = frames.light_direction[indices]
        if frames.light_intensity is None:
            intensity = np.ones((len(indices), 3))
        else:
            intensity = frames.light_intensity[indices]
        per_rgb = intensity[:, :, None] * direction[:, None, :]
        kind = "instantaneous"
    else:
        if capture.lights is None:
            raise UserError(f"frameps: {capture.path or 'the capture'} has exposure windows but no light model")
        model = build_light_model(capture.lights)
        if model.near:
            raise UserError(f"frameps: light model {model.name!r} is a near light; frameps needs directional lights")
        assert frames.t_start_us is not None and frames.t_end_us is not None
        per_rgb = np.stack(
            [equivalent_lights(model, frames.t_start_us[k], frames.t_end_us[k]) for k in indices]
        )
        kind = "equivalent"
    if channels == 1:
        per_rgb = np.einsum("c,kcx->kx", np.asarray(GREY_WEIGHTS), per_rgb)[:, None, :]
    return per_rgb, kind
