"""The ring light's model from the events of a chrome sphere during its turns (``sphere-events``).

While the ring turns, the sphere's highlight runs around it and its pixels fire. Per time window
(``window_us``; default 1/180 of the light period the capture states, else of its span) the events
on the sphere are counted per event pixel, smoothed (``smooth_px``), and the highlight is the region
around the densest point above ``level`` of its peak; its pixels, mapped into the frame through the
capture's event→frame affine, give a direction (``pstoolkit.hardware.highlight``) at the mean time
of its events. The directions over the turn(s) are fitted to the ``ring`` model, or to ``near-ring``
(``model=near-ring``, with the rig's ``pixel_pitch_mm`` and the sphere's ``radius_mm``, resting on
the plane z = 0 unless ``centre_z_mm`` says otherwise), by ``pstoolkit.hardware.ringfit``.

The sphere is the circle ``sphere=cx,cy,r`` in frame pixels, else the outline of the capture's
ground-truth mask: a chrome sphere under a moving light shows a ring of highlights, not its
silhouette, so a real recording names its circle.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar

import numpy as np

import psfmt
from psfmt.camera import PERSPECTIVE
from pstoolkit.errors import UserError
from pstoolkit.grid import default_affine
from pstoolkit.hardware.calibrate import apply_affine
from pstoolkit.hardware.highlight import mirror_direction
from pstoolkit.hardware.lightcal import LightCalibration, LightFit
from pstoolkit.hardware.ringfit import fit_near_ring, fit_ring
from pstoolkit.hardware.sphere import Circle, SphereView, circle_from_mask, parse_circle
from pstoolkit.hardware.sphere_frames import read_intrinsics
from pstoolkit.plugin.options import Option

WINDOWS_PER_TURN = 180
TOP_PERCENTILE = 99.0
"""The rise the track threshold is a fraction of (a percentile, so that a hot pixel does not set it)."""
MAX_WINDOWS = 1 << 20
MAX_SENSOR_PIXELS = 1 << 26
MODELS = ("ring", "near-ring")


def _circle(capture: psfmt.Capture, given: str, path: Path) -> tuple[Circle, np.ndarray | None]:
    if given:
        return parse_circle(given), None
    truth = capture.ground_truth
    if truth is not None and truth.mask is not None:
        return circle_from_mask(np.asarray(truth.mask, dtype=bool), f"{path}: ground-truth mask")
    raise UserError(f"{path}: give the sphere's outline with --sphere cx,cy,r (frame pixels); the capture has no mask")


def _window_us(capture: psfmt.Capture, option: float, span_us: float) -> float:
    if option > 0:
        return option
    period = None
    if capture.lights is not None:
        value = capture.lights.params.get("period_us")
        try:
            period = float(value) if value is not None else None
        except (TypeError, ValueError):
            period = None
    base = period if period is not None and np.isfinite(period) and period > 0 else span_us
    return max(base / WINDOWS_PER_TURN, 1.0)


def pixel_peaks(
    events: psfmt.Events, pixel_index: np.ndarray, turn_us: float, level_in: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per sphere pixel and turn: the time its brightness peaked and how many contrast steps it rose.

    A pixel's log brightness is its running sum of polarities (in contrast steps, from ``level_in``
    (P,), updated in place, the sum carried over from before). Within a turn its peak lies between
    the last ON event at the maximum and the next (OFF) event; the time is the midpoint of the ON
    event one step below the maximum and the first OFF event after it, which cross the same level
    on the way up and down, so a symmetric pulse gives its centre. Returns sphere-pixel indices,
    peak times (µs) and rises (steps), one entry per pixel and turn with events. Memory holds one
    turn's events at a time."""
    first, last = int(events.t_first_us or 0), int(events.t_last_us or 0)
    out_pixel, out_time, out_rise = [], [], []
    width = events.width
    t0 = first
    while t0 <= last:
        t1 = t0 + max(int(np.ceil(turn_us)), 1)
        chunk = events.window(t0, t1)
        t0 = t1
        if len(chunk) and (int(chunk.x.max()) >= width or int(chunk.y.max()) >= events.height):
            raise UserError(f"an event at ({int(chunk.x.max())}, {int(chunk.y.max())}) lies beyond the {width}×{events.height} sensor")
        where = pixel_index[chunk.y.astype(np.int64) * width + chunk.x]
        on = where >= 0
        if not on.any():
            continue
        pix, t, p = where[on], chunk.t[on].astype(np.float64), chunk.p[on].astype(np.int64)
        order = np.argsort(pix, kind="stable")
        pix, t, p = pix[order], t[order], p[order]
        starts = np.flatnonzero(np.r_[True, pix[1:] != pix[:-1]])
        group = np.repeat(np.arange(len(starts)), np.diff(np.r_[starts, len(pix)]))
        total = np.cumsum(p)
        before = np.r_[0, total][starts]
        level = total - before[group] + level_in[pix[starts]][group]
        highest = np.maximum.reduceat(level, starts)
        index = np.arange(len(pix))
        at_max = np.minimum.reduceat(np.where(level == highest[group], index, len(pix)), starts)
        ends = np.r_[starts[1:], len(pix)] - 1
        below = np.where(at_max > starts, at_max - 1, at_max)
        after = np.where(at_max < ends, at_max + 1, at_max)
        lowest = np.minimum(np.minimum.reduceat(level, starts), level_in[pix[starts]])
        out_pixel.append(pix[starts])
        out_time.append(0.5 * (t[below] + t[after]))
        out_rise.append((highest - lowest).astype(np.float64))
        level_in[pix[ends]] = level[ends]
    if not out_pixel:
        return np.empty(0, np.int64), np.empty(0), np.empty(0)
    return np.concatenate(out_pixel), np.concatenate(out_time), np.concatenate(out_rise)


class SphereEvents(LightCalibration):
    """Chrome sphere under the turning ring, events → a fitted ``ring`` or ``near-ring`` model."""

    name: ClassVar[str] = "sphere-events"
    summary: ClassVar[str] = "chrome sphere under the turning ring (events): highlight track fitted to the ring model"
    options: ClassVar[tuple[Option, ...]] = (
        Option("sphere", str, "", "the sphere's outline cx,cy,r in frame pixels (default: the ground-truth mask's)"),
        Option("intrinsics", str, "", "K.txt of a pinhole frame camera (default: the capture's, else orthographic)"),
        Option("model", str, "ring", "the light model fitted: ring (far field) or near-ring", choices=MODELS),
        Option("window_us", float, 0.0, "time window per highlight position, µs (0: 1/180 of the light period)", minimum=0.0),
        Option("level", float, 0.9, "track threshold: pixels whose rise over a turn exceeds this fraction of the highest", minimum=0.05, maximum=0.99),
        Option("min_pixels", int, 2, "windows with fewer track pixels peaking in them are skipped", minimum=1),
        Option("pixel_pitch_mm", float, 0.0, "near-ring: mm per frame pixel on the object plane", minimum=0.0),
        Option("radius_mm", float, 0.0, "near-ring: the sphere's radius in mm (default: its radius in pixels × pitch)", minimum=0.0),
        Option("centre_z_mm", float, -1.0, "near-ring: height of the sphere's centre above z = 0 (default: its radius, resting on it)"),
    )

    @classmethod
    def accepts(cls, source: Path) -> bool:
        if not source.is_file():
            return False
        try:
            with psfmt.read(source) as capture:
                return capture.events is not None and len(capture.events) > 0
        except (psfmt.FormatError, OSError):
            return False

    def calibrate(self, source: Path, **options: Any) -> LightFit:
        if not source.is_file():
            raise UserError(f"{source}: no such capture file")
        with psfmt.read(source) as capture:
            events = capture.events
            if events is None or len(events) == 0:
                raise UserError(f"{source}: holds no events of the sphere")
            circle, outline = _circle(capture, options["sphere"], source)
            calibration = capture.calibration
            fallback = calibration.intrinsics if calibration.camera_model == PERSPECTIVE else None
            sphere = SphereView.build(circle, read_intrinsics(options["intrinsics"], fallback), outline)
            frame_shape = (capture.frames.height, capture.frames.width) if capture.frames is not None else (events.height, events.width)
            affine = calibration.event_to_frame if calibration.event_to_frame is not None else default_affine(events.width, frame_shape[1])
            t_us, directions = self._track(capture, events, sphere, affine, options)
        return self._fit(t_us, directions, circle, frame_shape, sphere, options, source)

    def _track(
        self, capture: psfmt.Capture, events: psfmt.Events, sphere: SphereView, affine: np.ndarray, options: dict[str, Any]
    ) -> tuple[np.ndarray, np.ndarray]:
        """Times (N,) and light directions (N, 3) of the highlight, one per window with enough events."""

        he, we = events.height, events.width
        if he * we > MAX_SENSOR_PIXELS:
            raise UserError(f"the event sensor's {we}×{he} pixels are more than the {MAX_SENSOR_PIXELS:,} calibration takes")
        ve, ue = np.mgrid[0:he, 0:we]
        frame_uv = apply_affine(affine, np.stack([ue.ravel(), ve.ravel()], axis=1).astype(np.float64))
        c = sphere.circle
        inside = (frame_uv[:, 0] - c.cx) ** 2 + (frame_uv[:, 1] - c.cy) ** 2 < max(c.r - 1.0, 1.0) ** 2
        if not inside.any():
            raise UserError("the sphere's outline holds no event pixel (check --sphere and the event→frame affine)")
        flat = np.flatnonzero(inside)
        pixel_index = np.full(he * we, -1, dtype=np.int64)
        pixel_index[flat] = np.arange(len(flat))
        t_first, t_last = int(events.t_first_us or 0), int(events.t_last_us or 0)
        span = max(float(t_last - t_first), 1.0)
        window_us = _window_us(capture, options["window_us"], span)
        if span / window_us >= MAX_WINDOWS:
            raise UserError(f"window_us {window_us:g} cuts the recording into more than {MAX_WINDOWS:,} windows")
        turn_us = min(window_us * WINDOWS_PER_TURN, span + 1.0)
        pixel, t_peak, rise = pixel_peaks(events, pixel_index, turn_us, np.zeros(len(flat), dtype=np.int64))
        # the track: pixels that rose most over their turn (the highlight's core passed them)
        threshold = options["level"] * float(np.percentile(rise, TOP_PERCENTILE)) if len(rise) else 0.0
        band = rise > threshold
        pixel, t_peak, weight = pixel[band], t_peak[band], rise[band] - threshold
        window = np.floor((t_peak - t_first) / window_us).astype(np.int64)
        order = np.argsort(window, kind="stable")
        pixel, t_peak, weight, window = pixel[order], t_peak[order], weight[order], window[order]
        times, directions = [], []
        for part in np.split(np.arange(len(window)), np.flatnonzero(np.diff(window)) + 1):
            if len(part) < options["min_pixels"]:
                continue
            uv = frame_uv[flat[pixel[part]]]
            directions.append(mirror_direction(uv[:, 0], uv[:, 1], weight[part], sphere))
            times.append(float(np.average(t_peak[part], weights=weight[part])))
        return np.array(times), np.array(directions).reshape(-1, 3)

    def _fit(
        self, t_us: np.ndarray, directions: np.ndarray, circle: Circle, frame_shape: tuple[int, int], sphere: SphereView,
        options: dict[str, Any], source: Path,
    ) -> LightFit:
        if options["model"] == "near-ring":
            pitch = options["pixel_pitch_mm"]
            if pitch <= 0:
                raise UserError("model near-ring needs the rig's pixel_pitch_mm (--set pixel_pitch_mm=…)")
            if sphere.intrinsics is not None:
                raise UserError("model near-ring is fitted through an orthographic camera; leave out the intrinsics")
            radius = options["radius_mm"] or circle.r * pitch
            height = options["centre_z_mm"] if options["centre_z_mm"] >= 0 else radius
            centre = np.array([(frame_shape[1] - 1) / 2.0, (frame_shape[0] - 1) / 2.0])
            centre_mm = np.array([(circle.cx - centre[0]) * pitch, (centre[1] - circle.cy) * pitch, height])
            normals = (directions + np.array([0.0, 0.0, 1.0]))
            normals /= np.linalg.norm(normals, axis=1, keepdims=True)
            fit = fit_near_ring(t_us, directions, centre_mm + radius * normals, pitch)
        else:
            fit = fit_ring(t_us, directions)
        details: dict[str, Any] = {
            "windows": fit.observations,
            "sphere_px": [circle.cx, circle.cy, circle.r],
            "camera": "orthographic" if sphere.intrinsics is None else "perspective",
            "max_residual_deg": fit.max_deg,
        }
        return LightFit(
            spec=fit.light.to_spec(),
            directions=directions,
            intensities=np.ones_like(directions),
            times_us=t_us,
            residual_deg=fit.rms_deg,
            details=details,
        )
