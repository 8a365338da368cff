"""An event sensor's noise besides its leak (``pstoolkit.sim.sensor.EventSensor``): shot-noise events,
whose rate rises in the dark, and hot pixels, drawn block by block of time and merged into the block's
signal events (``NoiseEvents.merge``, ``merge_sorted``); and the leak of pixels whose light never
changes (``static_leak``), for an engine that does not step them.

Both event engines (``pstoolkit.sim.esim``, ``pstoolkit.sim.ring_engine``) call it once per block, so
memory stays bounded by a block's events: candidates are drawn as a Poisson process at the highest
per-pixel rate, at most ``CANDIDATES`` at a time, and thinned to each pixel's rate at its level then
(Lewis & Shedler's thinning). A noise event is dropped when it falls within the refractory period
after the pixel's previous event, signal or noise; noise events neither move the pixel's reference
level nor blind it for its signal. The merged block stays sorted by (µs, pixel), signal events first
among equals. The same sensor, seed and blocks give the same events."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from psfmt import EventArray
from pstoolkit.sim.sensor import SHOT_NOISE_BRIGHT_FACTOR, EventSensor

# Most candidate noise events drawn at once; a longer or busier block is drawn in parts.
CANDIDATES = 1 << 20

LevelAt = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""``level(pixel (M,), t_us (M,)) -> (M,)`` the irradiance ``I`` (not its log) a pixel sees at a time."""


class NoiseEvents:
    """The noise of ``sensor`` on a ``width``×``height`` event grid whose pixels have the thresholds
    ``c_pos``, ``c_neg`` (``EventSensor.thresholds``). State: each pixel's last event time, so the
    refractory period carries across blocks."""

    def __init__(self, sensor: EventSensor, width: int, height: int, c_pos: np.ndarray, c_neg: np.ndarray) -> None:
        n = width * height
        self.width, self.n_pixels = width, n
        self.refractory_us = float(sensor.refractory_us)
        _, _, self.rng_shot, self.rng_hot = sensor.rngs()
        factors = sensor.rate_factors(n)
        # per pixel and polarity, events per µs in the dark (v2e: half each way, more for a lower threshold)
        half = 0.5e-6 * sensor.shot_noise_hz * factors
        self.shot_rates = np.stack([half * sensor.contrast_pos / c_pos, half * sensor.contrast_neg / c_neg])
        self.shot_peak = float(self.shot_rates.max()) if sensor.shot_noise_hz > 0 else 0.0
        hot_count = self.rng_hot.binomial(n, sensor.hot_pixel_fraction) if sensor.hot_pixel_hz > 0 else 0
        self.hot_pixels = np.sort(self.rng_hot.choice(n, hot_count, replace=False)) if hot_count else np.empty(0, np.int64)
        self.hot_per_us = 1e-6 * sensor.hot_pixel_hz
        self.last_us = np.full(n, -np.inf)

    def _shot(self, ta: float, tb: float, level: LevelAt | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        rng, rate = self.rng_shot, self.shot_peak
        parts = []
        expected = 2.0 * rate * self.n_pixels * (tb - ta)
        pieces = max(1, math.ceil(expected / CANDIDATES))
        edges = np.linspace(ta, tb, pieces + 1)
        for a, b in zip(edges[:-1], edges[1:]):
            count = rng.poisson(2.0 * rate * self.n_pixels * (b - a))
            pix = rng.integers(0, self.n_pixels, count)
            t = rng.uniform(a, b, count)
            negative = rng.integers(0, 2, count)
            u = rng.uniform(0.0, 1.0, count)
            odds = self.shot_rates[negative, pix] / rate
            if level is not None and count:
                bright = np.minimum(level(pix, t), 1.0)
                odds = odds * (1.0 - (1.0 - SHOT_NOISE_BRIGHT_FACTOR) * bright)
            keep = u < odds
            parts.append((pix[keep], t[keep], (1 - 2 * negative[keep]).astype(np.int8)))
        return tuple(np.concatenate(c) for c in zip(*parts))  # type: ignore[return-value]

    def _hot(self, ta: float, tb: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        rng = self.rng_hot
        count = rng.poisson(self.hot_per_us * self.hot_pixels.size * (tb - ta)) if self.hot_pixels.size else 0
        pix = self.hot_pixels[rng.integers(0, max(self.hot_pixels.size, 1), count)]
        t = rng.uniform(ta, tb, count)
        return pix, t, (2 * rng.integers(0, 2, count) - 1).astype(np.int8)

    def merge(self, ta: float, tb: float, signal: EventArray, level: LevelAt | None = None) -> EventArray:
        """The block [``ta``, ``tb``) µs: ``signal`` (its events, sorted by (µs, pixel)) with the noise
        events drawn for it, sorted by (µs, pixel), signal first among equals. ``level`` gives the
        irradiance for the shot noise's dependence on light (None: dark everywhere)."""
        draws = [self._shot(ta, tb, level)] if self.shot_peak > 0 else []
        if self.hot_pixels.size:
            draws.append(self._hot(ta, tb))
        pix, t, pol = (np.concatenate(c) for c in zip(*draws)) if draws else (np.empty(0, np.int64),) * 3
        t_us = np.floor(np.asarray(t, np.float64) + 0.5).astype(np.int64)
        sig_pix = signal.y.astype(np.int64) * self.width + signal.x
        keep = self._outside_dead_time(pix, t_us, sig_pix, signal.t)
        pix, t_us, pol = pix[keep], t_us[keep], np.asarray(pol, np.int8)[keep]
        self._remember(sig_pix, signal.t)
        self._remember(pix, t_us)
        return merge_sorted(signal, pix, t_us, pol, self.width)

    def _outside_dead_time(self, pix: np.ndarray, t_us: np.ndarray, sig_pix: np.ndarray, sig_t: np.ndarray) -> np.ndarray:
        """(M,) bool: which noise events (pixel, µs) fall after the refractory period of the pixel's
        previous event — from earlier blocks, of ``signal`` (pixel, µs), or a noise event kept before."""
        if self.refractory_us == 0 or not len(pix):
            return np.ones(len(pix), bool)
        order = np.lexsort((t_us, pix))
        pix, t_us = pix[order], t_us[order]
        previous = self.last_us[pix].copy()
        if len(sig_t):
            sig_order = np.lexsort((sig_t, sig_pix))
            sp, st = sig_pix[sig_order], sig_t[sig_order]
            # the pixel's last signal event at or before each noise event, by one key of (pixel, µs)
            t_min = min(int(st.min()), int(t_us.min()))
            span = max(int(st.max()), int(t_us.max())) - t_min + 1
            j = np.searchsorted(sp * span + (st - t_min), pix * span + (t_us - t_min), side="right") - 1
            j0 = np.maximum(j, 0)
            same = (j >= 0) & (sp[j0] == pix)
            previous = np.where(same, np.maximum(previous, st[j0]), previous)
        # noise events of one pixel in turn: a kept one blinds the next ones
        start = np.r_[0, np.flatnonzero(np.diff(pix)) + 1]
        rank = np.arange(len(pix)) - np.repeat(start, np.diff(np.r_[start, len(pix)]))
        group = np.repeat(np.arange(len(start)), np.diff(np.r_[start, len(pix)]))
        group_last = np.full(len(start), -np.inf)
        keep = np.zeros(len(pix), bool)
        for k in range(int(rank.max()) + 1):
            i = np.flatnonzero(rank == k)
            g = group[i]
            ok = t_us[i] >= np.maximum(previous[i], group_last[g]) + self.refractory_us
            keep[i] = ok
            group_last[g[ok]] = t_us[i][ok]
        out = np.empty(len(pix), bool)
        out[order] = keep
        return out

    def _remember(self, pix: np.ndarray, t_us: np.ndarray) -> None:
        if len(pix):
            order = np.lexsort((t_us, pix))
            pix, t_us = pix[order], t_us[order]
            last = np.r_[np.flatnonzero(np.diff(pix)), len(pix) - 1]
            self.last_us[pix[last]] = np.maximum(self.last_us[pix[last]], t_us[last])


def merge_sorted(events: EventArray, pixel: np.ndarray, t_us: np.ndarray, polarity: np.ndarray, width: int) -> EventArray:
    """``events`` (sorted by (µs, pixel)) and the events ``pixel`` (y·width + x), ``t_us``, ``polarity``
    together, sorted by (µs, pixel), ``events`` first among equals (the sort is stable)."""
    if not len(t_us):
        return events
    all_pixel = np.concatenate((events.y.astype(np.int64) * width + events.x, pixel))
    all_t = np.concatenate((events.t, t_us))
    order = np.lexsort((all_pixel, all_t))
    all_pixel = all_pixel[order]
    return EventArray(x=all_pixel % width, y=all_pixel // width, t=all_t[order],
                      p=np.concatenate((events.p, np.asarray(polarity, np.int8)))[order])


def static_leak(
    pixels: np.ndarray, leak_per_us: np.ndarray, start: np.ndarray, c_pos: np.ndarray, sensor: EventSensor,
    ta: float, tb: float,
) -> tuple[np.ndarray, np.ndarray]:
    """The leak events in [``ta``, ``tb``) µs of ``pixels`` whose light never changes (from time 0):
    (pixel, µs) in no order. A pixel's L drifts up by ``leak_per_us`` against its reference, which starts
    ``start`` below its level, so it first fires at ``(C⁺ − start)/leak_per_us`` and then every
    ``C⁺/leak_per_us``, plus the refractory period under "reset-at-end" (the reference resets at its
    end), at least the refractory period under "rate-limited" — what an engine stepping the pixel gives."""
    rate = leak_per_us[pixels]
    live = rate > 0
    pixels, rate = pixels[live], rate[live]
    c = c_pos[pixels]
    first = (c - start[pixels]) / rate
    r = float(sensor.refractory_us)
    spacing = c / rate
    if r > 0:
        spacing = np.maximum(spacing, r) if sensor.paced else spacing + r
    k0 = np.maximum(np.ceil((ta - first) / spacing), 0.0)
    k1 = np.ceil((tb - first) / spacing)
    count = np.maximum(k1 - k0, 0).astype(np.int64)
    owner = np.repeat(np.arange(len(pixels)), count)
    k = k0[owner] + np.arange(owner.size) - np.repeat(np.cumsum(count) - count, count)
    t = first[owner] + k * spacing[owner]
    return pixels[owner], np.floor(t + 0.5).astype(np.int64)
