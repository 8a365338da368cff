"""Scrubbing a capture over time: the frame whose exposure covers t, the events around t, and the
light at t from the capture's light model, for the page to render the solver's prediction under.

``Timeline`` keeps the capture open (``psfmt.read``: lazy, so a frame or an event window is read
when the page asks for it) and serialises reads with a lock, as the server answers requests on
several threads. Times are integer microseconds. A capture whose frames carry their own
instantaneous lights (a DiLiGenT-style capture) is scrubbed by frame index instead of time.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from pathlib import Path
from typing import Any

import numpy as np

import psfmt
from psfmt.text import printable
from pstoolkit.errors import UserError
from pstoolkit.view.display import to_display
from pstoolkit.view.source import MAX_PIXELS

MAX_WINDOW_US = 200_000
"""Longest event window one request reads (longer ones are cut to it)."""
READ_STEP_US = 10_000
"""Events are read and counted this much time at a time, so memory is bounded by the busiest 10 ms,
not by the window."""
DEFAULT_WINDOW_US = 2_000
FRAME_CACHE = 4
"""Display frames kept: scrubbing back and forth within a few frames reads none again."""
MAX_ABS_TIME_US = 1 << 53
MAX_NOTES = 20


class Timeline:
    """The time axis of a capture at ``path``, for a result of (H, W) ``shape_hw`` (None: the
    frames' size, else the event sensor's; only a near light's direction depends on it).

    Raises UserError (or psfmt's FormatError) when the capture cannot be read or has a frame or
    sensor larger than ``MAX_PIXELS``. Call ``close`` when done."""

    def __init__(self, path: Path, shape_hw: tuple[int, int] | None = None) -> None:
        self.path = path
        self._lock = threading.Lock()
        self._frames_cache: OrderedDict[int, bytes] = OrderedDict()
        self.capture = psfmt.read(path)
        try:
            self._setup(shape_hw)
        except BaseException:
            self.capture.close()
            raise

    def _setup(self, shape_hw: tuple[int, int] | None) -> None:
        capture = self.capture
        frames, events = capture.frames, capture.events
        if frames is not None and frames.height * frames.width > MAX_PIXELS:
            raise UserError(f"{self.path}: {frames.width}×{frames.height} frames are over the viewer's {MAX_PIXELS} pixels")
        if events is not None and events.width * events.height > MAX_PIXELS:
            raise UserError(f"{self.path}: a {events.width}×{events.height} event sensor is over the viewer's {MAX_PIXELS} pixels")
        self.notes: list[str] = []
        self.model: Any = None
        if capture.lights is not None:
            from pstoolkit.optics.lights import build_light_model

            try:
                self.model = build_light_model(capture.lights)
            except Exception as exc:  # an unknown or malformed model: scrub frames and events without a prediction
                self.notes.append(f"light model {printable(capture.lights.model)!r} unusable: {printable(exc)}")
        self.by_frame = frames is not None and not frames.has_windows and frames.has_instant_lights
        # A near light's direction differs per pixel; the page shades with one, the one at the centre.
        if frames is not None:
            h, w = frames.height, frames.width
        else:
            h, w = shape_hw if shape_hw is not None else (events.height, events.width) if events is not None else (1, 1)
        self._centre = np.zeros((1, 3))
        if self.model is not None and getattr(self.model, "near", False) and hasattr(self.model, "pixel_points"):
            self._centre = self.model.pixel_points(h, w)[[(h // 2) * w + w // 2]]
        starts, ends = [], []
        if frames is not None and frames.has_windows:
            starts.append(int(frames.t_start_us.min()))
            ends.append(int(frames.t_end_us.max()))
        if events is not None and len(events):
            starts.append(int(events.t_first_us))
            ends.append(int(events.t_last_us) + 1)
        self.span_us = (min(starts), max(ends)) if starts else None

    def info(self) -> dict[str, Any]:
        """The page's description of the axis: ``mode`` (``time``, ``frames`` or ``none``), the span
        in µs, the frames (count, size, exposure windows) and events (sensor size, count)."""
        frames, events = self.capture.frames, self.capture.events
        mode = "frames" if self.by_frame else "time" if self.span_us is not None else "none"
        return {
            "path": str(self.path),
            "kind": self.capture.kind,
            "mode": mode,
            "span_us": list(self.span_us) if self.span_us is not None else None,
            "frames": None if frames is None else {
                "count": frames.count,
                "width": frames.width,
                "height": frames.height,
                "windows": np.stack([frames.t_start_us, frames.t_end_us], axis=1).tolist() if frames.has_windows else None,
            },
            "events": None if events is None else {"width": events.width, "height": events.height, "count": len(events)},
            "window_us": DEFAULT_WINDOW_US,
            "light_model": None if self.capture.lights is None else str(self.capture.lights.model),
            "notes": self.notes,
        }

    def at(self, t_us: int | None = None, frame: int | None = None) -> dict[str, Any]:
        """The frame index and light at time ``t_us`` (or at ``frame`` when frames carry their own
        lights): ``{"t_us", "frame", "light": [x, y, z] unit or None, "intensity": [r, g, b] or None}``.
        ``frame`` is None when no exposure covers t. Raises ValueError for an out-of-range input."""
        frames = self.capture.frames
        if self.by_frame:
            if frame is None or not 0 <= frame < frames.count:
                raise ValueError("frame index out of range")
            direction = frames.light_direction[frame]
            intensity = frames.light_intensity[frame] if frames.light_intensity is not None else np.ones(3)
            return {"t_us": None, "frame": frame, "light": _unit(direction), "intensity": _rgb(intensity)}
        if t_us is None or abs(t_us) > MAX_ABS_TIME_US:
            raise ValueError("time out of range")
        index = None
        if frames is not None and frames.has_windows:
            covering = np.flatnonzero((frames.t_start_us <= t_us) & (t_us < frames.t_end_us))
            index = int(covering[0]) if covering.size else None
        light = intensity = None
        if self.model is not None:
            with self._lock:
                try:
                    times = np.array([t_us], dtype=np.float64)
                    if getattr(self.model, "near", False):
                        direction, rgb = self.model.evaluate(times, self._centre)
                    else:
                        direction, rgb = self.model.evaluate(times)
                    light, intensity = _unit(np.reshape(direction, -1)[:3]), _rgb(np.reshape(rgb, -1)[:3])
                except Exception as exc:  # a plugin's model failing at some t: no prediction there
                    if len(self.notes) < MAX_NOTES:
                        self.notes.append(f"light model failed at t = {t_us} µs: {printable(exc)}")
        return {"t_us": t_us, "frame": index, "light": light, "intensity": intensity}

    def frame_rgb(self, k: int) -> bytes:
        """Frame ``k`` as display RGB bytes (H·W·3, row-major): the stored value over the
        saturation level, black level removed, through ``to_display`` (grey for one channel).
        Raises ValueError for an index out of range."""
        frames = self.capture.frames
        if frames is None or not 0 <= k < frames.count:
            raise ValueError("frame index out of range")
        with self._lock:
            if k in self._frames_cache:
                self._frames_cache.move_to_end(k)
                return self._frames_cache[k]
            linear = frames.as_float(k)
            rgb = np.repeat(linear[..., :1], 3, axis=2) if linear.shape[2] < 3 else linear[..., :3]
            data = to_display(rgb).tobytes()
            self._frames_cache[k] = data
            if len(self._frames_cache) > FRAME_CACHE:
                self._frames_cache.popitem(last=False)
            return data

    def events_rgb(self, t0_us: int, t1_us: int) -> bytes:
        """The events with t0 ≤ t < t1 (cut to ``MAX_WINDOW_US``) as RGB bytes at the sensor's size:
        positive events red, negative blue, each brightening with the pixel's count up to the 99th
        percentile of the counts; black where none fired. Raises ValueError without events."""
        events = self.capture.events
        if events is None:
            raise ValueError("the capture has no events")
        t0 = max(int(t0_us), -MAX_ABS_TIME_US)
        t1 = min(int(t1_us), t0 + MAX_WINDOW_US)
        size = events.width * events.height
        counts = np.zeros((2, size), dtype=np.int64)
        with self._lock:
            for start in range(t0, t1, READ_STEP_US):
                part = events.window(start, min(start + READ_STEP_US, t1))
                inside = (part.x < events.width) & (part.y < events.height)  # a file read without verify may hold strays
                pixel = part.y[inside].astype(np.int64) * events.width + part.x[inside]
                positive = part.p[inside] > 0
                counts[0] += np.bincount(pixel[positive], minlength=size)
                counts[1] += np.bincount(pixel[~positive], minlength=size)
        fired = counts[counts > 0]
        top = max(float(np.percentile(fired, 99.0)), 1.0) if fired.size else 1.0
        level = np.clip(counts / top, 0.0, 1.0)
        rgb = np.zeros((size, 3), dtype=np.uint8)
        rgb[:, 0] = to_display(level[0])
        rgb[:, 1] = (0.25 * to_display(np.maximum(level[0], level[1]))).astype(np.uint8)  # a little green: lone events stay visible
        rgb[:, 2] = to_display(level[1])
        return rgb.tobytes()

    def close(self) -> None:
        self.capture.close()


def _unit(vector: np.ndarray) -> list[float] | None:
    v = np.asarray(vector, dtype=np.float64)
    norm = float(np.linalg.norm(v))
    return (v / norm).tolist() if np.isfinite(norm) and norm > 0 else None


def _rgb(values: np.ndarray) -> list[float] | None:
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    if v.size == 1:
        v = np.repeat(v, 3)
    return v[:3].tolist() if v.size >= 3 and np.all(np.isfinite(v)) else None
