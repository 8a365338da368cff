"""Semi-real hybrid captures from a DiLiGenT object (the EventPS paper's semi-real recipe with DualResPS's
frames).

The 36 lights on the boundary of DiLiGenT's 12×8 light grid, in loop order, are the key lights of
one light period T; key light j is on at ``knots_us[j] = round(j·T/36)``. The images are cropped to a
square around the mask (16 px margin), area-resized to size×size, divided by the light intensities
and scaled so that the 99th percentile of all masked values of the 36 images is 1. Between key
lights each pixel's log-irradiance ``ln(I + ε)`` runs linearly in time, which defines I(t) for:

- **frames**: ``frames`` long exposures per period, frame k the mean of I(t) over
  [k·T/frames, (k+1)·T/frames) (exact: the integral of an exponential is closed-form), through the
  frame sensor of the configuration (``pstoolkit.sim.sensor.FrameSensor``; the ``ideal`` preset's:
  times 255, rounded and clamped to 8 bit): an LDR camera whose white (saturation, above the black
  level) is the 99th-percentile irradiance;
- **events**: grey = 0.299 R + 0.587 G + 0.114 B area-averaged to the event grid
  (``size·event_scale`` pixels a side), log-interpolated the same way and fed to the ESIM-style
  generator with the configured event sensor (thresholds and their spread, refractory period and
  rule, leak, shot noise, hot pixels);
- **discrete lights** (the frame-based comparison): K of the 36 key images, evenly spread over the
  loop, as instantaneous frames of the same scale and sensor.

The capture's light model is ``sampled``, periodic, through the key directions with intensity 1
(the images are already divided by the intensities); the ground truth is resized and re-normalised.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import psfmt
from pstoolkit import GREY_WEIGHTS, Progress, SampledLight, UserError
from pstoolkit.events.rule import log_irradiance
from pstoolkit.grid import area_weights, event_shape
from pstoolkit.sim.esim import simulate_events
from pstoolkit.sim.keyed import event_render, key_times_us, window_mean
from pstoolkit.sim.sensor import FRAME_BIT_DEPTHS, FrameSensor
from pstoolkit.sim.timing import CaptureTiming, append_event_chunks
from pstoolkit_diligent.folder import ObjectFolder
from pstoolkit_diligent.geometry import area_resize, crop, resize_truth, square_around

# Share of the progress bar given to reading and normalising the key images; the events take the rest.
FRAMES_SHARE = 0.25

GRID_LIGHTS = 96
BOUNDARY_LOOP: tuple[int, ...] = (
    *range(88, 96), 87, 79, 71, 63, 55, 7, 15, 23, 31, 39, 47, *range(46, 39, -1), 32, 24, 16, 8, 0, 48, 56, 64, 72, 80
)
"""The 0-based ids of the 36 boundary lights of the 12×8 grid (id = 8·column + row), in loop order."""
MARGIN_PX = 16
NORMALISE_PERCENTILE = 99.0


@dataclass
class SemiRealConfig(CaptureTiming):
    """Options of a semi-real capture (see the module docstring); ``discrete_lights`` K > 0 writes
    the frames-only comparison instead of the hybrid capture."""

    size: int = 256

    def check(self) -> None:
        """Raise UserError naming the first option out of range."""
        self.check_with([
            ("--frames", 1 <= self.frames <= 36, "must be between 1 and 36"),
            ("--period-ms", self.period_us >= 10 * len(BOUNDARY_LOOP), "is too short (at least 10 µs per key light)"),
            ("--discrete-lights", 0 <= self.discrete_lights <= len(BOUNDARY_LOOP), f"must be between 0 and {len(BOUNDARY_LOOP)}"),
        ])


@dataclass
class KeyLights:
    """The 36 boundary images as normalised linear irradiance (36, S, S, 3) float32 with their unit
    directions (36, 3), and the ground truth at S×S."""

    images: np.ndarray
    directions: np.ndarray
    normal: np.ndarray | None
    mask: np.ndarray


def check_grid(obj: ObjectFolder) -> None:
    """UserError unless ``obj`` has the 96 lights of DiLiGenT's grid, whose boundary the recipe uses."""
    if len(obj.images) != GRID_LIGHTS:
        raise UserError(f"{obj.path}: semi-real data needs DiLiGenT's {GRID_LIGHTS}-light grid, the folder has {len(obj.images)} lights")


def key_lights(obj: ObjectFolder, size: int, progress: Progress) -> KeyLights:
    """Crop, resize, divide and normalise the boundary images of ``obj`` (a 96-light object)."""
    check_grid(obj)
    square = square_around(obj.mask, MARGIN_PX)
    images = np.empty((len(BOUNDARY_LOOP), size, size, 3), dtype=np.float32)
    for j, k in enumerate(BOUNDARY_LOOP):
        images[j] = area_resize(crop(obj.image(k), square), size) / obj.intensities[k].astype(np.float32)
        progress((j + 1) / len(BOUNDARY_LOOP), "images")
    normal = crop(obj.normal, square) if obj.normal is not None else None
    normal, mask = resize_truth(normal, crop(obj.mask, square), size)
    level = float(np.percentile(images[:, mask], NORMALISE_PERCENTILE)) if mask.any() else 0.0
    if not level > 0:
        raise UserError(f"{obj.path}: the boundary images are black inside the mask")
    images /= np.float32(level)
    return KeyLights(images, obj.directions[list(BOUNDARY_LOOP)], normal, mask)


def knot_times_us(period_us: int) -> np.ndarray:
    """(37,) int64: the time of each key light in the first period, then the period's end."""
    return key_times_us(period_us, len(BOUNDARY_LOOP))


def ldr(irradiance: np.ndarray, sensor: FrameSensor, rng: np.random.Generator) -> np.ndarray:
    """Pixels of normalised irradiance through ``sensor``: 1.0 is its saturation, brighter clips."""
    return sensor.quantise(irradiance * sensor.signal_range(), rng)


def boundary_light(keys: KeyLights, knots_us: np.ndarray, period_us: int) -> psfmt.LightSpec:
    """The periodic ``sampled`` light model through the key directions, intensity 1."""
    light = SampledLight(
        times_us=knots_us[:-1],
        directions=keys.directions,
        intensities=np.ones_like(keys.directions),
        periodic=True,
        period_us=float(period_us),
    )
    return light.to_spec()


def write_semi_real(
    obj: ObjectFolder, writer: psfmt.CaptureWriter, config: SemiRealConfig, progress: Progress
) -> int:
    """Write the semi-real capture of ``obj`` through ``writer``; returns the number of events."""
    keys = key_lights(obj, config.size, lambda f, m: progress(FRAMES_SHARE * f, m))
    period = config.period_us
    knots = knot_times_us(period)
    sensor = config.frame_sensor()
    writer.begin_frames(config.size, config.size, 3, FRAME_BIT_DEPTHS[sensor.bit_depth], bit_depth=sensor.bit_depth,
                        black_level=sensor.black_level)
    rng = np.random.default_rng(np.random.SeedSequence(config.seed).spawn(1)[0])
    count = 0
    if config.discrete_lights:
        pick = np.arange(config.discrete_lights) * len(BOUNDARY_LOOP) // config.discrete_lights
        writer.append_frames(
            ldr(keys.images[pick], sensor, rng), light_direction=keys.directions[pick], light_intensity=np.ones((len(pick), 3))
        )
    else:
        log_rgb = log_irradiance(keys.images)
        bounds = config.exposure_bounds_us()
        means = [window_mean(log_rgb, knots, bounds[k], bounds[k + 1]) for k in range(config.frames)]
        for p in range(config.periods):
            # each period's frames draw their own noise
            for k, mean in enumerate(means):
                writer.append_frames(ldr(mean, sensor, rng), t_start_us=[p * period + bounds[k]],
                                     t_end_us=[p * period + bounds[k + 1]])
        count = _write_events(keys, knots, config, writer, progress)
    writer.set_lights(boundary_light(keys, knots, period))
    writer.set_ground_truth(psfmt.GroundTruth(normal=keys.normal, mask=keys.mask))
    progress(1.0, "done")
    return count


def _write_events(
    keys: KeyLights, knots_us: np.ndarray, config: SemiRealConfig, writer: psfmt.CaptureWriter, progress: Progress
) -> int:
    height, width = event_shape(config.size, config.size, config.event_scale)
    av = area_weights(height, config.size, config.event_scale)
    au = area_weights(width, config.size, config.event_scale)
    grey = keys.images.astype(np.float64) @ np.array(GREY_WEIGHTS)
    log_keys = log_irradiance(av @ grey @ au.T)
    chunks = simulate_events(
        event_render(log_keys, knots_us, config.period_us),
        0,
        config.duration_us,
        width=width,
        height=height,
        sensor=config.sensor(),
        min_dt_us=config.min_step_us,
    )
    count = append_event_chunks(
        writer, (height, width), ((c, float(c.t[-1])) for c in chunks), config.duration_us,
        lambda fraction, message: progress(FRAMES_SHARE + (1.0 - FRAMES_SHARE) * fraction, message),
    )
    writer.set_calibration(config.calibration())
    return count
