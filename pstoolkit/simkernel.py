"""The simulator's compiled engine: events and long exposures of a scene under a ring light in one
pass per event pixel (numba, in parallel over event pixels).

It covers what the simulator renders on the CPU with the built-in BRDFs (``ggx``, ``lambertian``):
a directional ring light, the closed-form shading of ``Renderer`` and the cast shadows of its shadow
grid. Other BRDFs, and other devices, go through ``Renderer`` and ``pstoolkit.esim``; both follow the
same event rule (``pstoolkit.eventmodel``) and ``tests/test_simkernel.py`` compares them.

Per event pixel, time advances in its own steps (ESIM's adaptive sampling, made per pixel): a step
whose change of the pixel's ``L = ln(I + ε)`` exceeds ``max_dlog`` (half the contrast) is shortened
until it does not or is ``min_dt_us`` long, and the next step grows or shrinks with the change of
this one, up to ``max_dt_us`` (8° of the turn) where no cast shadow can reach the pixel during the
block, else up to one interval of the shadow grid, so no sweep is stepped over; L may also leave
the previous step's line by at most ``MAX_BEND``. ``I`` is the area average of the frame pixels
under the event pixel, each shaded in closed form at the step's time; crossings are placed exactly on the line between samples, with the
refractory rule "reset-at-end". Each frame pixel belongs to the event pixel covering most of it, and
its ∫ V·[n·l]₊ dt and ∫ V·[n·l]₊·ratio dt (``ratio`` the GGX specular factor) accumulate by the
trapezoid rule on that pixel's samples: the exposures come from the same shading as the events.

Work per event pixel is about (number of steps) × (frame pixels under it): a pixel that sees no
change takes ``max_dt_us`` steps, one that fires takes about two steps per event. Memory: the
per-pixel state, a cast-shadow table for the current block of time, and the block's events (at most
``capacity`` per pixel; a block that overflows is run again with more room).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import numba
import numpy as np
import torch

from psfmt import EventArray
from pstoolkit.brdf import GGX
from pstoolkit.errors import UserError
from pstoolkit.esim import check_options, draw_thresholds, event_rngs
from pstoolkit.eventmodel import GREY_WEIGHTS, LOG_EPS
from pstoolkit.lights import RingLight
from pstoolkit.render import Renderer, event_shape

# Columns of the per-frame-pixel constants (``FrameConstants.values``).
NX, NY, NZ, GREY_DIFFUSE, GREY_SPECULAR, NORM2, ALPHA2_1, K, ONE_K, VIEW = range(10)
# Longest step of a pixel that no cast shadow can reach in the current block, as a share of the light's
# turn (a pixel that may be shadowed steps at most one shadow-grid interval, so no sweep is stepped over).
MAX_STEP_TURNS = 8.0 / 360.0
# Largest distance of L from the line of a pixel's previous step at the end of the next one: the line
# between the step's samples is then within about a quarter of it (1e-3) of L, so events keep the
# threshold rule where L curves (a highlight) even when its change over the step is small.
MAX_BEND = 4e-3
# Event pixels handed to a thread at a time: pixels differ a lot in work (a dark background pixel
# against one a shadow edge sweeps), so threads take small chunks as they finish instead of equal shares.
PIXELS_PER_TASK = 64
# Length of a block of time, in shadow-grid intervals: one shadow table and one batch of events.
BLOCK_GRID_STEPS = 32
# Keeps the half vector's normalisation finite when l = −v, as in ``pstoolkit.brdf``.
HALF_EPS = 1e-12


@dataclass
class FrameConstants:
    """Per masked frame pixel, what the closed form needs (``values`` (P, 10) float64, columns named
    above): normal, grey of e·albedo and of e·F0, |n|², α² − 1, k, 1 − k and α²/(4π G1-denominator of
    n·v); ``specular`` False for a Lambertian scene (the GGX columns unused)."""

    values: np.ndarray
    specular: bool


@dataclass
class Footprints:
    """Which masked frame pixels each event pixel averages: ``pixel`` (E, K) positions into the masked
    frame pixels (−1 for an unused slot), ``weight`` (E, K) area weights, ``owned`` (E, K) whether this
    event pixel integrates that frame pixel's exposure (each frame pixel has exactly one owner)."""

    pixel: np.ndarray
    weight: np.ndarray
    owned: np.ndarray


@dataclass
class PixelState:
    """Where each event pixel stands at the start of a block (all at the same time): its level ``level``
    (L at that time), firing levels ``hi``/``lo`` (±inf while blind), ``blind_until_us`` (inf unless a
    reset is pending), next step ``step_us``, slope of L over the last step ``slope`` (per µs,
    NaN before the first); and per masked frame pixel its last V·[n·l]₊ and
    V·[n·l]₊·ratio (``shade``, (P, 2)) and the exposure sums of the current window (``sums``, (P, 2),
    µs)."""

    level: np.ndarray
    hi: np.ndarray
    lo: np.ndarray
    blind_until_us: np.ndarray
    step_us: np.ndarray
    slope: np.ndarray
    shade: np.ndarray
    sums: np.ndarray

    def copy(self) -> PixelState:
        return PixelState(*(np.array(getattr(self, name)) for name in self.__dataclass_fields__))


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _direction(t_us: float, ring: tuple) -> tuple[float, float]:  # pragma: no cover - compiled
    cos_e, _, phase, omega, t0 = ring
    phi = phase + omega * (t_us - t0)
    return cos_e * math.cos(phi), cos_e * math.sin(phi)


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _shade_taps(
    t_us: float, p: int, pixel: np.ndarray, weight: np.ndarray, values: np.ndarray, specular: bool,
    ring: tuple, openness: np.ndarray, grid: tuple, shadowed: bool, out: np.ndarray,
) -> float:  # pragma: no cover - compiled
    """Grey irradiance of event pixel ``p`` at ``t_us``; ``out`` (K, 2) gets each frame pixel's
    V·[n·l]₊ and V·[n·l]₊·ratio."""
    lx, ly = _direction(t_us, ring)
    sin_e = ring[1]
    hz = 1.0 + sin_e
    ss = lx * lx + ly * ly + hz * hz
    inv_h = 1.0 / math.sqrt(ss + HALF_EPS)
    hh = ss / (ss + HALF_EPS)
    lift = HALF_EPS / (ss + HALF_EPS)
    x = t_us / grid[0] - grid[1]
    row = min(max(int(math.floor(x)), 0), openness.shape[0] - 2)
    after = x - row
    grey = 0.0
    for q in range(pixel.shape[1]):
        f = pixel[p, q]
        if f < 0:
            break
        across = values[f, NX] * lx + values[f, NY] * ly
        nl = across + values[f, NZ] * sin_e
        if nl <= 0.0:
            out[q, 0] = 0.0
            out[q, 1] = 0.0
            continue
        ratio = 0.0
        if specular:
            nh = (across + values[f, NZ] * hz) * inv_h
            d = nh * nh * values[f, ALPHA2_1] + lift + hh * values[f, NORM2]
            ratio = values[f, VIEW] / (d * d * (values[f, K] + nl * values[f, ONE_K]))
        if shadowed:
            v = openness[row, f] * (1.0 - after) + openness[row + 1, f] * after
            nl *= min(max(v, 0.0), 1.0)
        out[q, 0] = nl
        out[q, 1] = nl * ratio
        grey += weight[p, q] * nl * (values[f, GREY_DIFFUSE] + ratio * values[f, GREY_SPECULAR])
    return grey


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _fire(
    ta: float, la: float, tb: float, lb: float, p: int, c_pos: float, c_neg: float, refractory_us: float,
    hi: np.ndarray, lo: np.ndarray, blind_until: np.ndarray, out_t: np.ndarray, out_p: np.ndarray, n: int,
) -> int:  # pragma: no cover - compiled
    """Events of pixel ``p`` on the line from (``ta``, ``la``) to (``tb``, ``lb``) by the rule of
    ``pstoolkit.eventmodel`` (as ``esim._Pixels`` applies it to whole sensors); returns the pixel's
    event count, storing the events that fit in ``out_t``/``out_p``."""
    if blind_until[p] <= tb:
        level = la + (lb - la) * (blind_until[p] - ta) / (tb - ta)
        hi[p] = level + c_pos
        lo[p] = level - c_neg
        blind_until[p] = np.inf
    if lb >= hi[p]:
        sign, a, b, first, gap = 1, la, lb, hi[p], c_pos
    elif lb <= lo[p]:
        sign, a, b, first, gap = -1, -la, -lb, -lo[p], c_neg
    else:
        return n
    slope = max((b - a) / (tb - ta), _TINY)
    if refractory_us > 0:
        gap = gap + slope * refractory_us
    count = int(math.floor((b - first) / gap)) + 1
    span = max(b - a, _TINY)
    capacity = out_t.shape[1]
    for i in range(count):
        if n < capacity:
            frac = min(max((first + i * gap - a) / span, 0.0), 1.0)
            out_t[p, n] = ta + frac * (tb - ta)
            out_p[p, n] = sign
        n += 1
    last = first + (count - 1) * gap
    if refractory_us == 0:
        reference = sign * last
    else:
        until = min(ta + (last - a) / slope, tb) + refractory_us
        if until > tb:
            hi[p] = np.inf
            lo[p] = -np.inf
            blind_until[p] = until
            return n
        reference = sign * (last + slope * refractory_us)
    hi[p] = reference + c_pos
    lo[p] = reference - c_neg
    return n


_TINY = np.finfo(np.float64).tiny


@numba.njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def _advance(
    ta: float, tb: float, pixel: np.ndarray, weight: np.ndarray, owned: np.ndarray, values: np.ndarray,
    specular: bool, ring: tuple, openness: np.ndarray, grid: tuple,
    c_pos: np.ndarray, c_neg: np.ndarray, refractory_us: float, eps: float, max_dlog: float, min_dt: float,
    max_dt: float, grid_dt: float, level: np.ndarray, hi: np.ndarray, lo: np.ndarray, blind_until: np.ndarray,
    step: np.ndarray, slope: np.ndarray, shade: np.ndarray, sums: np.ndarray, out_t: np.ndarray, out_p: np.ndarray,
    count: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """Every event pixel from ``ta`` to ``tb`` (see the module docstring); state arrays are updated in
    place, events go to ``out_t``/``out_p`` and their numbers to ``count``."""
    taps = pixel.shape[1]
    for p in numba.prange(pixel.shape[0]):
        n = 0
        if pixel[p, 0] < 0:
            count[p] = 0
            continue
        now = np.empty((taps, 2))
        # a pixel that no cast shadow reaches during the block (V = 1 at every grid time) may take long
        # steps and skips the table
        shadowed = False
        for q in range(taps):
            f = pixel[p, q]
            if f < 0 or shadowed:
                break
            for row in range(openness.shape[0]):
                if openness[row, f] < 1.0:
                    shadowed = True
                    break
        longest = grid_dt if shadowed else max_dt
        t, l0, h, s0 = ta, level[p], min(step[p], longest), slope[p]
        while t < tb:
            left = tb - t
            h_try = left if (h >= left or left - h < min_dt) else h
            while True:
                t1 = tb if h_try >= left else t + h_try
                grey = _shade_taps(t1, p, pixel, weight, values, specular, ring, openness, grid, shadowed, now)
                l1 = math.log(grey + eps)
                change = abs(l1 - l0)
                # how far L left the line of the previous step: 4× the error of the line between samples
                bend = 0.0 if math.isnan(s0) else abs(l1 - l0 - s0 * (t1 - t))
                if h_try > min_dt and (change > max_dlog or bend > MAX_BEND):
                    shrink = min(0.9 * max_dlog / max(change, max_dlog), math.sqrt(0.9 * MAX_BEND / max(bend, MAX_BEND)))
                    h_try = max(min_dt, h_try * max(0.2, shrink))
                    continue
                break
            if l1 >= hi[p] or l1 <= lo[p] or blind_until[p] <= t1:
                n = _fire(t, l0, t1, l1, p, c_pos[p], c_neg[p], refractory_us, hi, lo, blind_until, out_t, out_p, n)
            for q in range(taps):
                f = pixel[p, q]
                if f < 0:
                    break
                if owned[p, q]:
                    sums[f, 0] += 0.5 * (shade[f, 0] + now[q, 0]) * (t1 - t)
                    sums[f, 1] += 0.5 * (shade[f, 1] + now[q, 1]) * (t1 - t)
                    shade[f, 0] = now[q, 0]
                    shade[f, 1] = now[q, 1]
            grow = min(2.0, 0.8 * max_dlog / max(change, 1e-12), math.sqrt(0.8 * MAX_BEND / max(bend, 1e-12)))
            h = min(longest, max(min_dt, h_try * max(0.5, grow)))
            s0 = (l1 - l0) / (t1 - t)
            t, l0 = t1, l1
        level[p] = l0
        step[p] = h
        slope[p] = s0
        count[p] = n


@numba.njit(cache=True, nogil=True)
def _start(
    t_us: float, pixel: np.ndarray, weight: np.ndarray, owned: np.ndarray, values: np.ndarray, specular: bool,
    ring: tuple, openness: np.ndarray, grid: tuple, shadows: bool, eps: float, level: np.ndarray,
    shade: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """Levels and frame-pixel shading at ``t_us`` (the start of the simulation)."""
    taps = pixel.shape[1]
    now = np.empty((taps, 2))
    for p in range(pixel.shape[0]):
        grey = _shade_taps(t_us, p, pixel, weight, values, specular, ring, openness, grid, shadows, now)
        level[p] = math.log(grey + eps)
        for q in range(taps):
            f = pixel[p, q]
            if f < 0:
                break
            if owned[p, q]:
                shade[f, 0] = now[q, 0]
                shade[f, 1] = now[q, 1]


@numba.njit(cache=True, nogil=True)
def _gather(out_t: np.ndarray, out_p: np.ndarray, count: np.ndarray, width: int,
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """The events of a block sorted by (µs, pixel): times rounded half up, then a counting sort on
    the µs (pixels visited in order, each pixel's events in time order, so ties keep pixel order
    and, within a pixel, emission order)."""
    total = 0
    t_min, t_max = np.iinfo(np.int64).max, np.iinfo(np.int64).min
    for p in range(count.shape[0]):
        for i in range(count[p]):
            t = np.int64(math.floor(out_t[p, i] + 0.5))
            t_min = min(t_min, t)
            t_max = max(t_max, t)
        total += count[p]
    x = np.empty(total, np.uint16)
    y = np.empty(total, np.uint16)
    t_out = np.empty(total, np.int64)
    p_out = np.empty(total, np.int8)
    if total == 0:
        return x, y, t_out, p_out
    slots = np.zeros(t_max - t_min + 2, np.int64)
    for p in range(count.shape[0]):
        for i in range(count[p]):
            slots[np.int64(math.floor(out_t[p, i] + 0.5)) - t_min + 1] += 1
    for k in range(1, slots.shape[0]):
        slots[k] += slots[k - 1]
    for p in range(count.shape[0]):
        for i in range(count[p]):
            t = np.int64(math.floor(out_t[p, i] + 0.5))
            j = slots[t - t_min]
            slots[t - t_min] += 1
            x[j] = p % width
            y[j] = p // width
            t_out[j] = t
            p_out[j] = out_p[p, i]
    return x, y, t_out, p_out


@dataclass
class Block:
    """What one block of time produced: its events (sorted by µs, then pixel), its end, and — when a
    window of ``window_ends_us`` ends with it — that window's (P, 2) sums ∫ V·[n·l]₊ dt and
    ∫ V·[n·l]₊·ratio dt per masked frame pixel (dt in µs)."""

    events: EventArray
    t_end_us: float
    window_sums: np.ndarray | None


def supported(renderer: Renderer) -> bool:
    """Whether ``simulate_ring`` can render this renderer's scene: a ring light, the ``ggx`` or
    ``lambertian`` BRDF in closed form, on the CPU, with cast shadows on a shadow grid (or none)."""
    return (
        isinstance(renderer.light, RingLight)
        and renderer.event_pixels_supported
        and renderer.device.type == "cpu"
    )


def frame_constants(renderer: Renderer) -> FrameConstants:
    """The closed form's per-pixel constants of ``renderer`` (its own, so the kernel shades as it does)."""
    c, rgb = renderer.closed_form_constants()
    e_grey = np.asarray(renderer.light.intensity, dtype=np.float64) * np.asarray(GREY_WEIGHTS)  # type: ignore[attr-defined]
    columns = {
        NX: c["nT"][0], NY: c["nT"][1], NZ: c["nT"][2],
        GREY_DIFFUSE: rgb["albedo"] @ torch.as_tensor(e_grey, dtype=torch.float64),
        GREY_SPECULAR: rgb["f0"] @ torch.as_tensor(e_grey, dtype=torch.float64),
        NORM2: c["nn"], ALPHA2_1: c["alpha2_1"], K: c["k"], ONE_K: c["1_k"], VIEW: c["dv"],
    }
    values = np.stack([columns[i].cpu().numpy() for i in range(len(columns))], axis=1)
    return FrameConstants(np.ascontiguousarray(values), isinstance(renderer.brdf, GGX))


def footprints(renderer: Renderer, event_scale: float) -> Footprints:
    """The event pixels' frame pixels (``Renderer.footprint``), unused slots last and marked −1, and
    each frame pixel's owner: the event pixel covering most of it (the first such on a tie)."""
    position, weight = (a.cpu().numpy() for a in renderer.footprint(event_scale))
    used = weight > 0
    order = np.argsort(~used, axis=1, kind="stable")
    position = np.take_along_axis(position, order, axis=1)
    weight = np.take_along_axis(weight, order, axis=1)
    used = np.take_along_axis(used, order, axis=1)
    pixel = np.where(used, position, -1)
    flat = np.flatnonzero(used.ravel())
    # among each frame pixel's slots the largest weight wins; lexsort puts it first
    by_pixel = np.lexsort((-weight.ravel()[flat], pixel.ravel()[flat]))
    slots = flat[by_pixel]
    first = np.ones(slots.size, dtype=bool)
    first[1:] = pixel.ravel()[slots][1:] != pixel.ravel()[slots][:-1]
    owned = np.zeros(pixel.size, dtype=bool)
    owned[slots[first]] = True
    return Footprints(np.ascontiguousarray(pixel), np.ascontiguousarray(weight), owned.reshape(pixel.shape))


def _ring(light: RingLight) -> tuple[float, float, float, float, float]:
    """The ring light as the kernels take it: (cos e, sin e, phase φ0 in rad, ω in rad/µs, t0 in µs),
    azimuth φ(t) = φ0 + ω·(t − t0) at elevation e."""
    e = math.radians(light.elevation_deg)
    omega = light.sense * 2.0 * math.pi / light.period_us
    return math.cos(e), math.sin(e), math.radians(light.phase_deg), omega, float(light.t0_us)


def _shadow_table(renderer: Renderer, ta: float, tb: float) -> tuple[np.ndarray, tuple[float, float]]:
    """Unclipped visibility (``render._openness`` of the shadow margins) of the masked frame pixels at
    the grid times around [ta, tb], (N, P) float32 rows for keys first, first + 1, …, and the grid
    (step µs, first key): V at a time is the linear mix of the two rows around it, clipped to [0, 1].
    Without cast shadows two rows of ones (V = 1 everywhere)."""
    if not renderer.shadows:
        return np.ones((2, renderer.pixels), dtype=np.float32), (1.0, 0.0)
    step = float(renderer.shadow_step_us)  # type: ignore[arg-type]
    first = math.floor(ta / step)
    return renderer.grid_openness(np.arange(first, math.floor(tb / step) + 2)), (step, float(first))


def simulate_ring(
    renderer: Renderer,
    *,
    event_scale: float,
    t1_us: float,
    window_ends_us: list[float],
    contrast_pos: float,
    contrast_neg: float,
    sigma: float = 0.0,
    refractory_us: float = 0.0,
    seed: int = 0,
    min_dt_us: float = 1.0,
    max_dt_us: float | None = None,
    max_dlog: float | None = None,
    eps: float = LOG_EPS,
    block_us: float | None = None,
    capacity: int = 8,
) -> Iterator[Block]:
    """Events of the event sensor at ``event_scale`` over [0, ``t1_us``] and the exposure sums of the
    windows ending at ``window_ends_us`` (increasing, inside (0, t1_us]), block by block in time
    order (see the module docstring). ``renderer`` must be ``supported``. ``max_dlog`` defaults to
    half the smaller contrast, ``max_dt_us`` (the longest step of a pixel no cast shadow reaches in
    the block; others step at most one shadow-grid interval) to ``MAX_STEP_TURNS`` of the turn,
    ``block_us`` to ``BLOCK_GRID_STEPS`` shadow-grid intervals; ``capacity`` is the first room for
    events per pixel and block (grown as needed). Thresholds are drawn as ``pstoolkit.esim`` draws
    them for ``seed``."""
    if not supported(renderer):
        raise UserError("simulate_ring needs a ring light, the ggx or lambertian BRDF, the CPU and a shadow grid")
    light = renderer.light
    assert isinstance(light, RingLight)
    if max_dlog is None:
        max_dlog = 0.5 * min(contrast_pos, contrast_neg)
    height, width = event_shape(renderer.maps.height, renderer.maps.width, event_scale)
    check_options(0.0, t1_us, width, height, {"contrast_pos": contrast_pos, "contrast_neg": contrast_neg}, sigma,
                  refractory_us, eps, max_dlog, 1.0, 2, min_dt_us, {}, caller="simulate_ring")
    ends = sorted({float(t) for t in window_ends_us} | {float(t1_us)})
    if ends[0] <= 0 or ends[-1] > t1_us:
        raise UserError(f"simulate_ring: window ends must lie in (0, t1_us = {t1_us}]")
    grid_dt_us = float(renderer.shadow_step_us or light.period_us / 360.0)
    if max_dt_us is None:
        max_dt_us = light.period_us * MAX_STEP_TURNS
    block_us = BLOCK_GRID_STEPS * grid_dt_us if block_us is None else float(block_us)
    constants = frame_constants(renderer)
    feet = footprints(renderer, event_scale)
    n_events = height * width
    c_pos, c_neg = draw_thresholds(event_rngs(seed)[0], contrast_pos, contrast_neg, sigma, n_events)
    ring = _ring(light)
    openness, grid = _shadow_table(renderer, 0.0, 0.0)
    state = PixelState(
        level=np.empty(n_events), hi=np.empty(n_events), lo=np.empty(n_events),
        blind_until_us=np.full(n_events, np.inf), step_us=np.full(n_events, max_dt_us / 4.0),
        slope=np.full(n_events, np.nan),
        shade=np.zeros((renderer.pixels, 2)), sums=np.zeros((renderer.pixels, 2)),
    )
    _start(0.0, feet.pixel, feet.weight, feet.owned, constants.values, constants.specular, ring, openness, grid,
           renderer.shadows, eps, state.level, state.shade)
    state.hi[:] = state.level + c_pos
    state.lo[:] = state.level - c_neg
    capacity = max(1, int(capacity))
    ta = 0.0
    for end in ends:
        while ta < end:
            tb = min(end, ta + block_us)
            if end - tb < 0.25 * block_us:
                tb = end
            openness, grid = _shadow_table(renderer, ta, tb)
            before = state.copy()
            while True:
                out_t = np.empty((n_events, capacity))
                out_p = np.empty((n_events, capacity), dtype=np.int8)
                count = np.zeros(n_events, dtype=np.int64)
                with numba.parallel_chunksize(PIXELS_PER_TASK):
                    _advance(ta, tb, feet.pixel, feet.weight, feet.owned, constants.values, constants.specular, ring,
                             openness, grid, c_pos, c_neg, float(refractory_us), float(eps),
                             float(max_dlog), float(min_dt_us), float(max_dt_us), grid_dt_us, state.level, state.hi, state.lo,
                             state.blind_until_us, state.step_us, state.slope, state.shade, state.sums, out_t, out_p, count)
                most = int(count.max(initial=0))
                if most <= capacity:
                    break
                # a pixel fired more than there was room for: run the block again with room for it
                capacity = most + most // 2
                state = before.copy()
            x, y, t, p = _gather(out_t, out_p, count, width)
            sums = None
            if tb == end and end in window_ends_us:
                sums, state.sums = state.sums, np.zeros_like(state.sums)
            yield Block(EventArray(x=x, y=y, t=t, p=p), tb, sums)
            ta = tb
