"""ESIM-style event simulation (Rebecq et al., ESIM, CoRL 2018) from a render callback.

``render(t_us) -> (T, height, width)`` gives linear grey irradiance (≥ 0) at the event resolution;
each pixel sees ``L = ln(I + ε)`` and fires by the rule of ``pstoolkit.events.rule``:

- **Sampling.** Render times are chosen adaptively: a block of up to ``chunk_samples`` times at the
  current step is rendered at once; every interval whose largest per-pixel ``|ΔL|`` exceeds
  ``max_dlog`` (default half the smaller contrast) is split into ``⌈|ΔL| / max_dlog⌉`` equal parts and
  the new times rendered, until no interval exceeds it or is shorter than ``min_dt_us``. The step of
  the next block follows the mean step of this one, doubled at most when the block changed little.
  Memory is bounded: ``render`` never receives more than ``chunk_samples`` times, and a few blocks
  of at most ``chunk_samples`` float32 log frames are held — never a (T × H × W) array of the whole
  span. As in ESIM, a change that starts and ends between two samples is not seen. The number of
  samples is set by the fastest pixel: a pixel leaving attached shadow (I from 0, so ln(I + ε)
  jumps by ≈ 7) forces steps near ``min_dt_us``, and the cost is about samples × pixels.
- **Per-pixel refinement** (optional ``render_pixels(t_us, pixel)``, single pixels at single times):
  a split interval's new times are rendered only for the pixels whose own ``|ΔL|`` over it exceeds
  ``max_dlog``; every other pixel takes the value on its line, which is what the rule above assumes
  of it anyway, so each pixel is sampled as finely as it needs and no finer. The whole-frame renders
  then follow the share of pixels needing refinement (see
  ``pstoolkit.sim.esim_sampling.adaptive_blocks``), or fixed times (``sample_times_us``), and a
  terminator sweeping the sensor costs a few pixels per fine step instead of whole frames.
- **Crossings.** ``L`` (held in float32, ≈ 1e-6 absolute) is linear between samples; every crossing
  inside a step is emitted at its own exact time on that line (float64), then rounded half up to
  int64 µs. Positive events step the reference by ``C⁺``, negative by ``C⁻``; per-pixel thresholds
  are drawn once from ``N(C, σ)`` and clamped to ≥ 0.01.
- **Refractory** (``refractory_rule``, one of ``pstoolkit.events.rule.REFRACTORY_RULES``): after an event at
  ``t`` the pixel cannot fire before ``t + R``. "reset-at-end" (the default): what happens in the
  dead time is not emitted, and at ``t + R`` the reference is reset to ``L(t + R)``; on a line of
  slope ``s`` a pixel fires every ``R + C / |s|``. "rate-limited": the reference moves by one
  threshold per event and a level still beyond a threshold at ``t + R`` fires then, so a line
  steeper than ``C / R`` fires every ``R`` while the reference lags behind (``pstoolkit.sim.esim_pixels.PacedPixels``: on
  each line between samples the events are the closed form of ``pstoolkit.sim.ring_engine``'s
  ``_fire_lanes_paced``). With ``R = 0`` the two are the same rule, ESIM's, and run as
  "reset-at-end".
- **Leak** (v2e-style, optional): each pixel's reference drifts down by its rate times its ``C⁺``
  per second, so a static pixel fires positive events at its leak rate (``EventSensor.leak_hz``,
  spread per pixel by ``rate_spread_decades``); the start reference is lowered by a uniform random
  fraction of ``C⁺`` (seeded) so that static pixels do not fire in lockstep. Leak events are
  threshold crossings: the refractory rule applies to them as to any.
- **Shot noise and hot pixels** (optional): ``pstoolkit.sim.event_noise.NoiseEvents`` draws them
  for each chunk, the shot noise's rate set by each pixel's irradiance on its lines between samples,
  and merges them into the chunk; a noise event within the refractory period after the pixel's
  previous event is not emitted.

Output: ``EventArray`` chunks in time order — each sorted by ``t`` and then by pixel (y·width + x),
each starting no earlier than the previous one ended; times lie in ``[t0_us, t1_us]``. The same
arguments and seed give the same events.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from functools import partial

import numpy as np

from psfmt import EventArray
from pstoolkit.errors import UserError
from pstoolkit.events.rule import log_irradiance
from pstoolkit.sim.esim_pixels import PacedPixels, Pixels
from pstoolkit.sim.esim_sampling import RenderPixels, adaptive_blocks
from pstoolkit.sim.event_noise import NoiseEvents
from pstoolkit.sim.sensor import EventSensor, check_sampling

Render = Callable[[np.ndarray], np.ndarray]


def _check_sample_times(sample_times_us: np.ndarray, t0_us: float, t1_us: float) -> np.ndarray:
    times = np.asarray(sample_times_us, dtype=np.float64).reshape(-1)
    if times.size and not (times[0] > t0_us and times[-1] < t1_us and np.all(np.diff(times) > 0)):
        raise UserError("simulate_events: sample_times_us must increase strictly inside (t0_us, t1_us)")
    return np.append(times, t1_us)


def _log_frames(render: Render, t_us: np.ndarray, shape: tuple[int, int], eps: float) -> np.ndarray:
    """``ln(I + ε)`` of the rendered frames, flattened to (T, H·W)."""
    irradiance = np.asarray(render(t_us))
    if irradiance.shape != (len(t_us), *shape):
        raise UserError(f"simulate_events: render returned shape {irradiance.shape}, expected {(len(t_us), *shape)}")
    if not (irradiance.min() >= 0 and np.isfinite(irradiance.max())):
        raise UserError("simulate_events: render returned negative or non-finite irradiance")
    return log_irradiance(irradiance, eps, np.float32).reshape(len(t_us), -1)


def _log_pixels(render_pixels: RenderPixels, t_us: np.ndarray, pixel: np.ndarray, eps: float) -> np.ndarray:
    """``ln(I + ε)`` of single pixels at single times, float32."""
    irradiance = np.asarray(render_pixels(t_us, pixel))
    if irradiance.shape != (len(t_us),):
        raise UserError(f"simulate_events: render_pixels returned shape {irradiance.shape}, expected {(len(t_us),)}")
    if not (irradiance.size == 0 or (irradiance.min() >= 0 and np.isfinite(irradiance.max()))):
        raise UserError("simulate_events: render_pixels returned negative or non-finite irradiance")
    return log_irradiance(irradiance, eps, np.float32)


def irradiance_on_lines(knots_us: np.ndarray, levels: np.ndarray, drift_per_us: np.ndarray, t0_us: float, eps: float,
                        ) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """``level(pixel, t_us)`` for ``pstoolkit.sim.event_noise.NoiseEvents``: the irradiance on the lines
    of L = ln(I + ``eps``) between the samples ``knots_us`` (S ≥ 2,) of ``levels`` (S, pixels), less
    the leak's drift ``drift_per_us`` (pixels,) since ``t0_us``."""

    def level(pixel: np.ndarray, t_us: np.ndarray) -> np.ndarray:
        j = np.clip(np.searchsorted(knots_us, t_us, side="right") - 1, 0, len(knots_us) - 2)
        w = (t_us - knots_us[j]) / (knots_us[j + 1] - knots_us[j])
        log_level = (1.0 - w) * levels[j, pixel] + w * levels[j + 1, pixel] - drift_per_us[pixel] * (t_us - t0_us)
        return np.maximum(np.exp(log_level) - eps, 0.0)

    return level


def _sorted_chunk(pix: np.ndarray, t: np.ndarray, pol: np.ndarray, width: int, n_pixels: int) -> EventArray:
    """Round times half up to µs and sort by (t, pixel); the sort is stable, so a pixel's events that
    round to the same µs keep their order."""
    t_us = np.floor(t + 0.5).astype(np.int64)
    key = (t_us - t_us.min()) * n_pixels + pix
    order = np.argsort(key, kind="stable")
    pix, t_us = pix[order], t_us[order]
    return EventArray(x=pix % width, y=pix // width, t=t_us, p=pol[order])


def simulate_events(
    render: Render,
    t0_us: float,
    t1_us: float,
    *,
    width: int,
    height: int,
    sensor: EventSensor | None = None,
    max_dlog: float | None = None,
    initial_dt_us: float = 100.0,
    chunk_samples: int = 64,
    min_dt_us: float = 1.0,
    render_pixels: RenderPixels | None = None,
    sample_times_us: np.ndarray | None = None,
) -> Iterator[EventArray]:
    """Events of a ``width``×``height`` sensor watching ``render`` from ``t0_us`` to ``t1_us`` (see the
    module docstring for the model). Yields non-empty ``EventArray`` chunks in time order.

    Parameters
    ----------
    render
        ``render(t_us (T,)) -> (T, height, width)`` linear grey irradiance (≥ 0).
    t0_us, t1_us
        The span simulated, µs.
    width, height
        The sensor's size in pixels.
    sensor
        The event sensor: thresholds, refractory period and rule, ε, noise rates and seed
        (default ``EventSensor()``).
    max_dlog
        Largest change of L allowed between samples (default half the smaller threshold).
    initial_dt_us
        The first sampling step, µs.
    chunk_samples
        The most times rendered or held at once.
    min_dt_us
        The shortest interval that is still split (a jump in irradiance is resolved to this), µs.
    render_pixels
        Optional ``render_pixels(t_us (M,), pixel (M,)) -> (M,)``, the irradiance of single pixels
        (``pixel`` = y·width + x) at single times: with it, refinement renders only the pixels that
        need it.
    sample_times_us
        Optional fixed times of the whole-frame renders (increasing, inside (t0_us, t1_us); t1_us is
        added) instead of the adaptive steps, so a caller can share them with other work (the
        simulator integrates its frames on them); refinement still applies.

    Raises
    ------
    UserError
        An option out of range, or a render of the wrong shape or with negative or non-finite values.
    """
    sensor = EventSensor() if sensor is None else sensor
    if max_dlog is None:
        max_dlog = sensor.half_contrast()
    sensor.check("simulate_events")
    check_sampling("simulate_events", t0_us, t1_us, width, height,
                   {"max_dlog": max_dlog, "initial_dt_us": initial_dt_us, "min_dt_us": min_dt_us}, chunk_samples)
    if sample_times_us is not None:
        sample_times_us = _check_sample_times(sample_times_us, float(t0_us), float(t1_us))
    n_pixels = width * height
    c_pos, c_neg = sensor.thresholds(n_pixels)
    eps = sensor.eps
    noise = NoiseEvents(sensor, width, height, c_pos, c_neg) if sensor.fires_noise else None

    def log_render(t_us: np.ndarray) -> np.ndarray:
        return _log_frames(render, t_us, (height, width), eps)

    l_start = log_render(np.array([float(t0_us)]))[0]
    # Leak is a downward drift of the reference; it is applied as the equal upward drift
    # leak_per_us·(t − t0) of the signal, which keeps the signal piecewise linear.
    leak_per_us = sensor.leak_per_us(c_pos)
    reference = l_start.astype(np.float64) - sensor.leak_start(c_pos)
    if sensor.paced:
        pixels: Pixels = PacedPixels(c_pos, c_neg, reference + c_pos, reference - c_neg, np.full(n_pixels, -np.inf),
                                     float(sensor.refractory_us))
    else:
        pixels = Pixels(c_pos, c_neg, (reference + c_pos).astype(np.float32), (reference - c_neg).astype(np.float32),
                        np.full(n_pixels, np.inf), float(sensor.refractory_us))

    t_prev, m_prev = float(t0_us), l_start
    log_render_pixels = None if render_pixels is None else partial(_log_pixels, render_pixels, eps=eps)

    for times, block in adaptive_blocks(log_render, log_render_pixels, float(t0_us), float(t1_us), l_start, max_dlog,
                                        float(initial_dt_us), float(min_dt_us), int(chunk_samples), sample_times_us):
        if sensor.leak_hz > 0:
            block += leak_per_us * (times - t0_us)[:, None]
        pix, t, pol = pixels.advance(t_prev, m_prev, times, block)
        chunk = _sorted_chunk(pix, t, pol, width, n_pixels) if len(t) else EventArray.empty()
        if noise is not None:
            level = irradiance_on_lines(np.concatenate(([t_prev], times)), np.vstack((m_prev[None], block)),
                                        leak_per_us, float(t0_us), eps)
            chunk = noise.merge(t_prev, float(times[-1]), chunk, level)
        t_prev, m_prev = float(times[-1]), block[-1]
        if len(chunk):
            yield chunk
