"""The height scale at which the estimated surface's cast shadows start and end when the events say.

A height map integrated from photometric normals comes out too shallow wherever the normals are
flattened — the classic effect of inter-reflection in a concavity, where light from the opposite wall
tilts a wall towards the camera — and its cast shadows then come out too short. The events know better
when a shadow starts and ends: its edge takes the direct light at once, so the pixel's next run of events
starts there, whatever light fills the shadow afterwards. A height map scaled by s predicts, at each
super pixel, the times its shadowed share crosses ``edge_tracking.SHARE_THRESHOLD``; ``calibrate`` scores each s by
Cohen's kappa of those crossings against the events' onsets (``onsets``): an entry meets a falling onset
within the tolerance, an exit a rising one, beyond the chance the onsets around it give. The scale moves
from 1 only where another clearly agrees better (``_choose``): a surface already right keeps s = 1 (its
edges match and a taller one's do not), and so does one whose events carry no edges (a rate-limited
pixel that fires every refractory period starts no run at a shadow) or that casts too few shadows to
count.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from pstoolkit._shared import devices
from pstoolkit.shadows.base import ShadowEvidence
from pstoolkit.shadows.device_tracking import DeviceEdgeTracker, edge_tracker
from pstoolkit.shadows.edge_tracking import EdgeTracker, SuperPixels
from pstoolkit.shadows.intervals import search_sorted
from pstoolkit.shadows.period_profile import Profile
from pstoolkit.shadows.silences import RUN_TOLERANCE_US, min_gap_us
from pstoolkit.shadows.surface_sweep import surface_shadow_blocks

# Fewest predicted edges a scale needs for its agreement to count.
MIN_EDGES = 50
# Width, in tolerances, of the span around an edge whose onsets set the chance of a match.
CHANCE_SPAN = 5.0
# Least agreement (Cohen's kappa) with the onsets a changed scale must reach, and least gain over 1's.
MIN_AGREEMENT = 0.35
MIN_GAIN = 0.05
# Standard errors of an agreement (binomial) a gain must exceed, and within which of the best a scale
# nearer 1 is taken instead.
SIGNIFICANCE = 2.0
# Scales tried first: a geometric grid from 1/2 to 2^1.5, 1 among them; the best is then refined
# halfway (in log) to each neighbour.
COARSE_SCALES = tuple(float(2.0 ** (k / 4.0)) for k in range(-4, 7))
# Light directions per period of the calibration's sweeps (2° of the turn: the tolerance is several).
CALIBRATION_STEPS = 180


@dataclass(frozen=True)
class HeightScale:
    """The chosen ``scale``, and per scale tried (increasing) the predicted edges and their agreement
    with the onsets (``matched``, Cohen's kappa)."""

    scale: float
    scales: tuple[float, ...]
    edges: tuple[int, ...]
    matched: tuple[float, ...]

    def record(self) -> dict[str, object]:
        return {"height_scale": round(self.scale, 4), "scales": [round(s, 4) for s in self.scales], "edges": list(self.edges),
                "matched": [round(m, 4) for m in self.matched]}


def period_keys(profile: Profile, chosen: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Sorted keys of the ``chosen`` (N,) bool events of ``profile`` (default all), falling and rising
    apart, as ``within`` searches them: pixel·3T + T + phase (T the period), each event entered three
    times, a period early, on time and a period late, so a search near either end of the period finds the
    events across it."""
    period = profile.period_us
    key = profile.pixel * 3.0 * period + period + profile.t_us
    chosen = np.ones(len(profile), dtype=bool) if chosen is None else chosen
    copies = (-period, 0.0, period)
    return tuple(np.sort(np.concatenate([key[chosen & (profile.p * sign > 0)] + c for c in copies])) for sign in (-1, 1))


def onsets(profile: Profile, refractory_us: float) -> tuple[np.ndarray, np.ndarray]:
    """``period_keys`` of the events that start a run: an event whose pixel's previous event
    (cyclically) has the other polarity or lies more than one refractory period (at least 200 µs,
    ``silences.min_gap_us``: a burst's events, R = 0, follow each other within it; and
    ``RUN_TOLERANCE_US``) before it."""
    previous, gap = profile.previous()
    return period_keys(profile, (profile.p != profile.p[previous]) | (gap > min_gap_us(-1.0, refractory_us, 1.0) + RUN_TOLERANCE_US))


def within(keys: np.ndarray, pixel: np.ndarray, phase_us: np.ndarray, period_us: float, half_width_us: float) -> np.ndarray:
    """(n,) int: the events of ``keys`` (``period_keys``) of each pixel within ``half_width_us`` of its
    phase."""
    centre = pixel * 3.0 * period_us + period_us + phase_us
    return search_sorted(keys, centre + half_width_us, side="right") - search_sorted(keys, centre - half_width_us)


def _matches(keys: np.ndarray, pixel: np.ndarray, phase_us: np.ndarray, period_us: float, tolerance_us: float
             ) -> tuple[np.ndarray, np.ndarray]:
    """Whether an onset lies within ``tolerance_us`` of each (pixel, phase), and the chance of that at
    a random time nearby: onsets arriving at the rate of those within ``CHANCE_SPAN`` tolerances around
    it, leaving out the tolerance itself (Poisson)."""
    near = within(keys, pixel, phase_us, period_us, tolerance_us)
    around = within(keys, pixel, phase_us, period_us, CHANCE_SPAN * tolerance_us) - near
    chance = 1.0 - np.exp(-around / (CHANCE_SPAN - 1.0))
    return near > 0, chance


def super_pixel_edges(evidence: ShadowEvidence, groups: SuperPixels, height: np.ndarray, time_steps: int, margin_px: float,
                      *, count_pixels: bool = False) -> EdgeTracker | DeviceEdgeTracker:
    """The ``EdgeTracker`` of the surface of ``height`` marched at ``time_steps`` directions (its device
    copy where the evidence's device sweeps, ``device_tracking``)."""
    tracker = edge_tracker(groups, evidence.device, count_pixels=count_pixels)
    for block in surface_shadow_blocks(evidence, height, time_steps, margin_px):
        tracker.feed(block)
    return tracker


def _kappa(falling: np.ndarray, rising: np.ndarray, phase_us: np.ndarray, pixel: np.ndarray, entering: np.ndarray,
           period_us: float, tolerance_us: float) -> float:
    """Cohen's kappa of the edges (``phase_us``, event ``pixel``, ``entering``; (n,) each) against the
    onsets (``onsets``), each edge matched (``_matches``) against those of its polarity, falling for an
    entry and rising for an exit: the matches beyond chance, as a share of what chance leaves."""
    met = np.zeros(len(pixel), dtype=bool)
    chance = np.zeros(len(pixel))
    for keys, which in ((falling, entering), (rising, ~entering)):
        met[which], chance[which] = _matches(keys, pixel[which], phase_us[which], period_us, tolerance_us)
    return float(np.sum(met - chance) / max(np.sum(1.0 - chance), 1e-9))


def kappa_there(falling: Tensor, rising: Tensor, phase_us: Tensor, pixel: Tensor, entering: Tensor, period_us: float,
                tolerance_us: float) -> float:
    """``_kappa`` of tensors on a device (float64 keys and phases, int64 pixels, bool entering): the same
    searches and sums, equal to rounding (the order of the device's sums)."""
    centre = pixel.to(torch.float64) * 3.0 * period_us + period_us + phase_us
    met = torch.zeros_like(entering)
    chance = torch.zeros_like(phase_us)

    def within_there(keys: Tensor, at: Tensor, half_width_us: float) -> Tensor:
        return torch.searchsorted(keys, at + half_width_us, right=True) - torch.searchsorted(keys, at - half_width_us)

    for keys, which in ((falling, entering), (rising, ~entering)):
        near = within_there(keys, centre[which], tolerance_us)
        around = within_there(keys, centre[which], CHANCE_SPAN * tolerance_us) - near
        met[which] = near > 0
        chance[which] = 1.0 - torch.exp(-around.to(torch.float64) / (CHANCE_SPAN - 1.0))
    # both sums in one read of the device
    beyond, left = torch.stack([torch.sum(met.to(torch.float64) - chance), torch.sum(1.0 - chance)]).tolist()
    return float(beyond / max(left, 1e-9))


def calibrate(evidence: ShadowEvidence, height: np.ndarray, *, margin_px: float, tolerance_deg: float = 10.0,
              time_steps: int = CALIBRATION_STEPS) -> HeightScale:
    """The height scale whose shadows' edges the events confirm best (module docstring).

    Parameters
    ----------
    evidence
        The capture's evidence (its events' ``profile``, super pixels, light, mask).
    height
        (H, W) height map in pixels of the current surface (``surface_sweep.surface_height``).
    margin_px
        The sweep's occluder margin (``surface_sweep.surface_shadow_blocks``).
    tolerance_deg
        How far, in degrees of the light's turn, an onset may lie from a predicted edge.
    time_steps
        Light directions per period the shadows are marched towards.

    Returns
    -------
    HeightScale
        The chosen scale (``_choose``) and the figures of every scale tried, in increasing order.
    """
    period = evidence.period_us
    tolerance_us = tolerance_deg / 360.0 * period
    groups = SuperPixels.shared(evidence)
    tried: dict[float, tuple[int, float]] = {}
    on_host = devices.on_host(evidence.device)
    if on_host:
        falling, rising = onsets(evidence.profile, evidence.refractory_us)
    else:
        # the device's tracker keeps its edges there: the onsets go to meet them, once for every surface
        falling, rising = evidence.of_capture(("onsets", str(evidence.device)), lambda: tuple(
            torch.as_tensor(keys, device=evidence.device) for keys in onsets(evidence.profile, evidence.refractory_us)))

    def agreement(scale: float) -> None:
        tracker = super_pixel_edges(evidence, groups, height * np.float32(scale), time_steps, margin_px)
        if on_host:
            bins, pixel, entering = tracker.edges()
            tried[scale] = (int(bins.size), _kappa(falling, rising, bins * (period / time_steps), pixel, entering, period,
                                                   tolerance_us))
        else:
            bins, pixel, entering = tracker.edges_there()
            tried[scale] = (int(bins.numel()), kappa_there(falling, rising, bins.to(torch.float64) * (period / time_steps),
                                                           pixel, entering, period, tolerance_us))

    for scale in COARSE_SCALES:
        agreement(scale)
    counted = [s for s in COARSE_SCALES if tried[s][0] >= MIN_EDGES]
    if counted:
        best = max(counted, key=lambda s: tried[s][1])
        for neighbour in (best / 2.0 ** 0.125, best * 2.0 ** 0.125):
            if COARSE_SCALES[0] < neighbour < COARSE_SCALES[-1]:
                agreement(neighbour)
    scales = tuple(sorted(tried))
    edges = [tried[s][0] for s in scales]
    matched = [tried[s][1] for s in scales]
    return HeightScale(scale=_choose(scales, edges, matched), scales=scales, edges=tuple(edges), matched=tuple(matched))


def _choose(scales: tuple[float, ...], edges: list[int], matched: list[float]) -> float:
    """1, unless some scale's agreement reaches ``MIN_AGREEMENT`` and beats 1's (0 when 1 predicts
    under ``MIN_EDGES`` edges) by ``MIN_GAIN`` and ``SIGNIFICANCE`` standard errors, and the best is not
    at either end of ``scales``; then, among the scales that beat it, the one nearest 1 whose agreement
    is within that many standard errors of the best's: a taller or flatter surface must earn its change."""
    def error(i: int) -> float:
        rate = min(max(matched[i], 0.0), 1.0)
        return float(np.sqrt(rate * (1.0 - rate) / max(edges[i], 1)))

    counted = [i for i, n in enumerate(edges) if n >= MIN_EDGES]
    reference = next((matched[i] for i in counted if scales[i] == 1.0), 0.0)
    better = [i for i in counted if matched[i] >= MIN_AGREEMENT
              and matched[i] - reference >= max(MIN_GAIN, SIGNIFICANCE * error(i))]
    if not better:
        return 1.0
    best = max(better, key=lambda i: matched[i])
    if best in (0, len(scales) - 1):
        # the rate still rises at the end of the range: its best lies beyond, or nowhere
        return 1.0
    close = [i for i in better if matched[i] >= matched[best] - SIGNIFICANCE * error(best)]
    return float(scales[min(close, key=lambda i: abs(np.log(scales[i])))])
