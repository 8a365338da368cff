"""What the ring-light engine's kernels read and update, grouped as ``NamedTuple`` records (numba
passes them as structs): the closed form's per-frame-pixel constants, the event pixels' footprints,
the ring light, the event rule, the step limits, the shadow table and the per-pixel state; and, as a
dataclass, what they take of the renderer's scene (``ShadedScene``)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numba
import numpy as np
import torch

from pstoolkit.optics.brdf import HALF_EPS
from pstoolkit.optics.grey import GREY_WEIGHTS
from pstoolkit.optics.lights import RingLight


@dataclass(frozen=True)
class ShadedScene:
    """What the kernels take of a renderer (``pstoolkit.sim.ring_engine.shaded_scene``): its closed
    form's per-pixel ``constants`` and float64 ``rgb`` albedo and F0 (``Renderer.closed_form_constants``),
    the light's RGB ``intensity`` (3,) float64, ``specular`` True for GGX (False: Lambertian), the
    masked frame pixels' flat positions row-major ``index`` (P,) and column-major ``index_t`` (P,)
    (``Renderer.column_major_index``), and the frame's ``height`` and ``width``."""

    constants: dict[str, torch.Tensor]
    rgb: dict[str, torch.Tensor]
    intensity: np.ndarray
    specular: bool
    index: np.ndarray
    index_t: np.ndarray
    height: int
    width: int


# Columns of the per-frame-pixel constants (``FrameConstants.values``).
NX, NY, NZ, GREY_DIFFUSE, GREY_SPECULAR, NORM2, ALPHA2_1, K, ONE_K, VIEW = range(10)


class FrameConstants(NamedTuple):
    """Per masked frame pixel, what the closed form needs (``values`` (P, 10) float64, columns named
    above): normal, grey of e·albedo and of e·F0, |n|², α² − 1, k, 1 − k and α²/(4π G1-denominator of
    n·v); ``specular`` False for a Lambertian scene (the GGX columns unused)."""

    values: np.ndarray
    specular: bool


class Footprints(NamedTuple):
    """Which masked frame pixels each event pixel averages: ``pixel`` (E, K) positions into the masked
    frame pixels (−1 for an unused slot), ``weight`` (E, K) area weights, ``owned`` (E, K) whether this
    event pixel integrates that frame pixel's exposure (each frame pixel has exactly one owner)."""

    pixel: np.ndarray
    weight: np.ndarray
    owned: np.ndarray


class FrameInputs(NamedTuple):
    """What a lane loads for an event pixel (``lanes.load_lane``): the ``FrameConstants`` ``values``
    (P, 10) and ``specular``, the ``Footprints`` ``pixel`` and ``weight`` (E, K), and the masked frame
    pixels' flat positions row- and column-major, ``index`` and ``index_t`` (P,) (the columns of a
    shadow table's row-major and column-major rows)."""

    values: np.ndarray
    weight: np.ndarray
    pixel: np.ndarray
    index: np.ndarray
    index_t: np.ndarray
    specular: bool


class RingParams(NamedTuple):
    """The ring light as the kernels take it: azimuth φ(t) = ``phase_rad`` + ``omega_rad_per_us``·(t −
    ``t0_us``) at elevation e (``cos_e``, ``sin_e``); then, as the closed form of ``Renderer`` needs them
    for the half vector h = l + v (whose length does not change on the ring), ``inv_half`` 1/|h|,
    ``half_share`` |h|²/(|h|² + ε) and ``eps_share`` ε/(|h|² + ε)."""

    cos_e: float
    sin_e: float
    phase_rad: float
    omega_rad_per_us: float
    t0_us: float
    inv_half: float
    half_share: float
    eps_share: float


class ShadowGrid(NamedTuple):
    """The times of a shadow table's rows: row i is at (``first`` + i)·``step_us``."""

    step_us: float
    first: float


class ShadowTable(NamedTuple):
    """Unclipped visibility of the frame pixels at the grid times of a block: ``openness`` (N, H·W)
    float32 rows, which of them are column-major ``column_major`` (N,), their times (``ShadowGrid``'s
    fields, flat: numba's parallel loops take no nested records), and per frame pixel (H·W,) the grid
    intervals in which a cast shadow falls on it while lit, ``reach`` (bits,
    ``shadow_table.lit_shadow``). V at a time is the linear mix of the two rows around it, clipped to
    [0, 1]."""

    openness: np.ndarray
    column_major: np.ndarray
    grid_step_us: float
    grid_first: float
    reach: np.ndarray


class EventRule(NamedTuple):
    """The event rule of ``pstoolkit.events.rule`` as the kernels apply it: per event pixel thresholds
    ``c_pos`` and ``c_neg`` (E,), the refractory period, whether it is "rate-limited" (``paced``;
    else "reset-at-end"), the ε of ``L = ln(I + ε)``, and the leak: each pixel's L drifts up against
    its reference by ``leak_per_us`` (E,) per µs since 0 when ``leaky``."""

    c_pos: np.ndarray
    c_neg: np.ndarray
    refractory_us: float
    paced: bool
    eps: float
    leak_per_us: np.ndarray
    leaky: bool


class StepLimits(NamedTuple):
    """A pixel's step control: the largest change of L a step may make ``max_dlog``, the shortest and
    longest steps ``min_dt_us``/``max_dt_us`` and the shadow grid's interval ``grid_dt_us``, the step
    around shadows."""

    max_dlog: float
    min_dt_us: float
    max_dt_us: float
    grid_dt_us: float


class PixelState(NamedTuple):
    """Where each event pixel stands at the start of a block (all at the same time): its level ``level``
    (L at that time), firing levels ``hi``/``lo`` and ``blind_until_us`` — for "reset-at-end" ±inf
    while blind and inf unless a reset is pending, for "rate-limited" always the reference ± C and
    the end of the blind time (−inf before the first event) —, next step ``step_us``, slope of L over
    the last step ``slope`` (per µs, NaN before the first); and per slot of its footprint (the frame pixels under it, see
    ``Footprints``) the last V·[n·l]₊ and V·[n·l]₊·ratio (``shade``, (E, K, 2)) and the exposure
    sums of the current window (``sums``, (E, K, 2), µs)."""

    level: np.ndarray
    hi: np.ndarray
    lo: np.ndarray
    blind_until_us: np.ndarray
    step_us: np.ndarray
    slope: np.ndarray
    shade: np.ndarray
    sums: np.ndarray


class EventRoom(NamedTuple):
    """Room for a block's events, per event pixel: times ``t_us`` (E, room) whole µs and polarities
    ``polarity`` (E, room), and how many each pixel fired ``count`` (E,) — more than the room when it
    overflowed (the pixel is then run again with more room)."""

    t_us: np.ndarray
    polarity: np.ndarray
    count: np.ndarray


def frame_constants(scene: ShadedScene) -> FrameConstants:
    """The closed form's per-pixel constants of the renderer's ``scene`` (its own, so the kernels shade as it does)."""
    c, rgb = scene.constants, scene.rgb
    e_grey = scene.intensity * np.asarray(GREY_WEIGHTS)
    columns = {
        NX: c["nT"][0], NY: c["nT"][1], NZ: c["nT"][2],
        GREY_DIFFUSE: rgb["albedo"] @ torch.as_tensor(e_grey, dtype=torch.float64),
        GREY_SPECULAR: rgb["f0"] @ torch.as_tensor(e_grey, dtype=torch.float64),
        NORM2: c["nn"], ALPHA2_1: c["alpha2_1"], K: c["k"], ONE_K: c["1_k"], VIEW: c["dv"],
    }
    values = np.stack([columns[i].cpu().numpy() for i in range(len(columns))], axis=1)
    return FrameConstants(np.ascontiguousarray(values), scene.specular)


def footprints(position: np.ndarray, weight: np.ndarray, pixels: int) -> Footprints:
    """The event pixels' frame pixels, ``position`` (E, K) into the ``pixels`` masked frame pixels with
    area ``weight`` (E, K) (``Renderer.footprint``), unused slots last and marked −1, and each frame
    pixel's owner: the event pixel covering most of it (the first such on a tie)."""
    position, weight = np.ascontiguousarray(position), np.ascontiguousarray(weight)
    pixel, ordered, owned = np.empty_like(position), np.empty_like(weight), np.zeros(position.shape, np.bool_)
    _order_slots(position, weight, pixels, pixel, ordered, owned)
    return Footprints(pixel, ordered, owned)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _order_slots(
    position: np.ndarray, weight: np.ndarray, pixels: int, pixel: np.ndarray, ordered: np.ndarray, owned: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """``footprints`` in one pass over the (E, K) slots: each event pixel's used slots (weight > 0)
    first, in their order, then the unused (position −1); the slot with a frame pixel's largest
    weight owns it, the first in flat order on a tie."""
    best = np.full(pixels, -np.inf)
    owner = np.full(pixels, -1, np.int64)
    taps = position.shape[1]
    for e in range(position.shape[0]):
        j = 0
        for used in (True, False):
            for q in range(taps):
                if (weight[e, q] > 0) == used:
                    pixel[e, j] = position[e, q] if used else -1
                    ordered[e, j] = weight[e, q]
                    j += 1
        for q in range(taps):
            f = pixel[e, q]
            if f >= 0 and ordered[e, q] > best[f]:
                best[f] = ordered[e, q]
                owner[f] = e * taps + q
    flat = owned.reshape(-1)
    for f in range(pixels):
        if owner[f] >= 0:
            flat[owner[f]] = True


def owner_slots(feet: Footprints) -> np.ndarray:
    """(P,): each masked frame pixel's owning slot, into the flattened (E, K) footprints."""
    slots = np.flatnonzero(feet.owned.ravel())
    # every masked pixel has exactly one owner, so the owned slots' pixels are a permutation of 0 … P − 1
    owner = np.empty_like(slots)
    owner[feet.pixel.ravel()[slots]] = slots
    return owner


def frame_inputs(scene: ShadedScene, constants: FrameConstants, feet: Footprints) -> FrameInputs:
    """The lanes' frame inputs of the renderer's ``scene`` from its constants and footprints."""
    return FrameInputs(constants.values, feet.weight, feet.pixel, scene.index, scene.index_t, constants.specular)


def ring_params(light: RingLight) -> RingParams:
    """``light`` as the kernels take it (``RingParams``)."""
    e = math.radians(light.elevation_deg)
    omega = light.sense * 2.0 * math.pi / light.period_us
    cos_e, sin_e = math.cos(e), math.sin(e)
    hh = cos_e * cos_e + (1.0 + sin_e) ** 2
    return RingParams(cos_e, sin_e, math.radians(light.phase_deg), omega, float(light.t0_us),
                      1.0 / math.sqrt(hh + HALF_EPS), hh / (hh + HALF_EPS), HALF_EPS / (hh + HALF_EPS))
