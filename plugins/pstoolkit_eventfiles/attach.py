"""What a converted event recording is joined with: frames, a light model and a calibration.

Frames come from a folder of images (exposure windows from the recording's trigger edges: a rising
edge opens a frame's exposure, the next falling edge on the same channel closes it) or from another
capture (its frames with their windows or light directions and sensor attributes). A light model or
calibration comes from a JSON file or another capture. Everything is read and checked before the
output is written.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np

import psfmt
from pstoolkit import Option, UserError
from pstoolkit.io.normalmap import decode_image

IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg", ".bmp", ".pgm", ".ppm")

ATTACH_OPTIONS = (
    Option("frames", str, "", "frames to attach: a folder of images (windows from triggers) or a capture .h5"),
    Option("trigger_channel", int, 0, "trigger channel whose rising/falling edges bound the folder frames' exposures", minimum=0, maximum=31),
    Option("lights", str, "", "light model: a JSON file {\"model\": NAME, \"params\": {…}} or a capture .h5"),
    Option("calibration", str, "", "calibration: a JSON file (event_to_frame, contrast_pos, …) or a capture .h5"),
)


def _is_capture(path: Path) -> bool:
    return path.suffix.lower() in (".h5", ".hdf5")


def _read_capture(path: Path) -> psfmt.Capture:
    if not path.is_file():
        raise UserError(f"{path}: does not exist")
    return psfmt.read(path)


def image_stack(folder: Path) -> tuple[np.ndarray, str]:
    """All images of ``folder`` in name order as (K, H, W, C) and their colour order."""
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise UserError(f"{folder}: holds no images ({', '.join(IMAGE_SUFFIXES)})")
    images = []
    for path in files:
        image = decode_image(path)
        if image is None:
            raise UserError(f"{path}: not a readable image")
        if image.dtype not in (np.uint8, np.uint16):
            raise UserError(f"{path}: {image.dtype} pixels; frames must be 8- or 16-bit")
        if image.ndim == 3 and image.shape[2] == 4:
            image = image[..., :3]
        image = image[..., ::-1] if image.ndim == 3 else image[..., None]
        if images and (image.shape != images[0].shape or image.dtype != images[0].dtype):
            raise UserError(f"{path}: {image.shape} {image.dtype} differs from {files[0].name} {images[0].shape} {images[0].dtype}")
        images.append(np.ascontiguousarray(image))
    stack = np.stack(images)
    return stack, "RGB" if stack.shape[3] == 3 else "L"


def trigger_windows(triggers: psfmt.Triggers, channel: int, count: int, where: Path) -> tuple[np.ndarray, np.ndarray]:
    """Exposure windows of ``count`` frames from the rising/falling edges of ``channel``."""
    on = triggers.channel == channel
    t, value = triggers.t[on], triggers.value[on]
    rising = np.flatnonzero(value == 1)
    starts, ends = [], []
    for r in rising:
        falling = np.flatnonzero(value[r + 1 :] == 0)
        if len(falling):
            starts.append(t[r])
            ends.append(t[r + 1 + falling[0]])
    if len(starts) != count:
        raise UserError(
            f"{where}: trigger channel {channel} gives {len(starts)} exposure window(s) for {count} frame(s)"
        )
    return np.asarray(starts, np.int64), np.asarray(ends, np.int64)


def load_frames(spec: str) -> psfmt.Frames | None:
    """The frames named by ``--frames``, in memory: a capture's with their windows or light directions
    and its sensor attributes (bit depth, saturation, black level, response), or a folder's, whose
    attributes are those of the images' data type and which still need ``time_frames``."""
    if not spec:
        return None
    path = Path(spec)
    if _is_capture(path):
        with _read_capture(path) as capture:
            frames = capture.frames
            if frames is None:
                raise UserError(f"{path}: holds no frames")
            return dataclasses.replace(frames, data=np.asarray(frames.data))
    if not path.is_dir():
        raise UserError(f"--frames {path}: neither a folder of images nor a capture .h5")
    data, order = image_stack(path)
    return psfmt.Frames(data, color_order=order)


def time_frames(frames: psfmt.Frames, triggers: psfmt.Triggers, channel: int, folder: Path) -> None:
    """Give the frames of ``folder`` their exposure windows from the recording's trigger edges."""
    if len(triggers) == 0:
        raise UserError(f"--frames {folder}: the recording has no trigger edges to time the frames")
    frames.t_start_us, frames.t_end_us = trigger_windows(triggers, channel, frames.count, folder)


def _json(path: Path, option: str) -> dict[str, Any]:
    try:
        value = json.loads(path.read_text())
    except FileNotFoundError:
        raise UserError(f"--{option} {path}: does not exist") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise UserError(f"--{option} {path}: not valid JSON ({exc})") from None
    if not isinstance(value, dict):
        raise UserError(f"--{option} {path}: expected a JSON object")
    return value


def load_lights(spec: str) -> psfmt.LightSpec | None:
    if not spec:
        return None
    path = Path(spec)
    if _is_capture(path):
        with _read_capture(path) as capture:
            if capture.lights is None:
                raise UserError(f"{path}: holds no light model")
            return capture.lights
    value = _json(path, "lights")
    if not isinstance(value.get("model"), str) or not isinstance(value.get("params", {}), dict):
        raise UserError(f"--lights {path}: expected {{\"model\": NAME, \"params\": {{…}}}}")
    return psfmt.LightSpec(value["model"], dict(value.get("params", {})))


CALIBRATION_KEYS = ("event_to_frame", "contrast_pos", "contrast_neg", "refractory_us", "camera_model", "view_direction")


def load_calibration(spec: str) -> psfmt.Calibration | None:
    if not spec:
        return None
    path = Path(spec)
    if _is_capture(path):
        with _read_capture(path) as capture:
            return capture.calibration
    value = _json(path, "calibration")
    unknown = sorted(set(value) - set(CALIBRATION_KEYS))
    if unknown:
        raise UserError(f"--calibration {path}: unknown key(s) {', '.join(unknown)} (known: {', '.join(CALIBRATION_KEYS)})")
    calibration = psfmt.Calibration(**value)
    if calibration.event_to_frame is not None and calibration.event_to_frame.shape != (2, 3):
        raise UserError(f"--calibration {path}: event_to_frame must be a 2×3 affine matrix")
    return calibration


def write_attachments(
    writer: psfmt.CaptureWriter,
    frames: psfmt.Frames | None,
    lights: psfmt.LightSpec | None,
    calibration: psfmt.Calibration | None,
) -> None:
    if frames is not None:
        writer.begin_frames(
            frames.height, frames.width, frames.channels, frames.data.dtype, color_order=frames.color_order,
            bit_depth=frames.bit_depth, saturation=frames.saturation, black_level=frames.black_level, response=frames.response,
        )
        writer.append_frames(
            frames.data,
            t_start_us=frames.t_start_us,
            t_end_us=frames.t_end_us,
            light_direction=frames.light_direction,
            light_intensity=frames.light_intensity,
        )
    if lights is not None:
        writer.set_lights(lights)
    if calibration is not None:
        writer.set_calibration(calibration)
