"""Cast shadows where the surface and the events agree (``fused``, the default of ``dualres``).

The surface (``geometry``) predicts every shadow at frame resolution but also shadows that a wrong
normal or a smoothed depth step invents; the events (``silences``) see every deep shadow of a super
pixel but also the dark spans of smooth shading. A frame pixel is taken to be in a cast shadow at a
time when both say so: the surface's shadow at that pixel, and a dark span (or no event at all over
the period) of the super pixel covering it. On simulated captures at the 2 ms recipe the mask of the
two together is far more precise than either alone (``benchmarks/dualres.py --ablation``). Before the
solver has a surface the detector returns no mask.

Light from the rest of the object fills the cast shadows of a concavity, and its events are not dark
there; so a shadow of the surface also counts where the events see its edges (``edge_seen``: a net fall
at its entry, a net rise at its exit). On a start's surface (the closed form's, before any fit) only at
the frame pixels it shadows for at most ``edge_share`` of the turn: a pixel shadowed longer keeps only what
a dark span confirms, because long shadows of a wrong surface leave a first fit a short, wrong lit arc to
fix a normal by. On a surface fitted to the measurements (``ShadowEvidence.fitted``, a solver's
re-detection) the limit is ``fitted_edge_share``, the whole turn by default (``docs/dualres-tuning.md``).

Inter-reflection also flattens the normals of a concavity, so the surface integrated from them comes out
too shallow and its shadows too short, more than one height scale for the whole surface makes up. Where
the solver takes inter-reflected light out (``ShadowEvidence.inter_reflected``: the hypothesis that the
capture has it), the mask also takes the confirmed shadows of the surface ``reflected_scale`` times taller.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import replace
from typing import Any, ClassVar

import numpy as np

from pstoolkit._shared import devices
from pstoolkit.plugin.options import Option
from pstoolkit.shadows.base import ShadowDetector, ShadowEvidence, ShadowMask
from pstoolkit.shadows.device_tracking import DeviceRunCollector, edge_tracker, run_collector
from pstoolkit.shadows.edge_seen import SeenShadows, seen_edges
from pstoolkit.shadows.edge_tracking import SuperPixels
from pstoolkit.shadows.geometry import GEOMETRY_OPTIONS, shadow_height
from pstoolkit.shadows.intervals import RunCollector, ShadowIntervals, intervals_from_grid, rasterize
from pstoolkit.shadows.silences import dark_spans, min_gap_us
from pstoolkit.shadows.surface_sweep import surface_shadow_blocks

# Frame pixels at a time whose surface shadows are checked against the seen ones on the host: a
# (steps, chunk) grid of bytes (5.9 MB at 720 steps); on a device, at most this many bytes of work.
SEEN_CHUNK = 8192
SEEN_BYTES = 1 << 30


def event_darkness(evidence: ShadowEvidence, steps: int, min_gap: float) -> np.ndarray:
    """(steps, He·We) bool: event pixels inside a dark span, or without events over the period."""
    n_events = evidence.event_shape[0] * evidence.event_shape[1]
    spans = dark_spans(evidence.profile, refractory_us=evidence.refractory_us, min_gap_us=min_gap)
    dark = rasterize(spans, n_events, evidence.period_us, steps)
    silent = np.ones(n_events, dtype=bool)
    silent[evidence.profile.pixel] = False
    # row by row: a column assignment strides across the whole map
    dark |= silent
    return dark


class FusedDetector(ShadowDetector):
    name: ClassVar[str] = "fused"
    summary: ClassVar[str] = "shadows of the estimated surface confirmed by dark spans or edges of the events"
    options: ClassVar[tuple[Option, ...]] = (
        *GEOMETRY_OPTIONS,
        Option("min_gap_ms", float, -1.0, "shortest dark span, ms (−1: one refractory period, at least 0.2 ms)", minimum=-1.0),
        Option("edge_share", float, 0.3, "a shadow whose edges the events see (more fall than rise within edge_tolerance_deg "
               "of its entry, more rise than fall of its exit) counts without a dark span at the pixels a start's "
               "surface (not yet fitted) shadows for at most this share of the turn (0: dark spans only)",
               minimum=0.0, maximum=1.0),
        Option("fitted_edge_share", float, 1.0, "the same limit on a surface fitted to the measurements (a re-detection)",
               minimum=0.0, maximum=1.0),
        Option("reflected_scale", float, 1.19, "where the solver takes inter-reflection out (ShadowEvidence.inter_reflected), "
               "also the confirmed shadows of a surface this much taller: inter-reflection flattens a concavity's normals, "
               "so the surface integrated from them comes out too shallow (1: none)", minimum=1.0, maximum=2.0),
    )
    uses_surface: ClassVar[bool] = True

    def detect(self, evidence: ShadowEvidence, options: dict[str, Any]) -> ShadowMask:
        if evidence.normal is None:
            return evidence.no_mask()
        # the height first: its solve is the detector's peak memory, better without the dark map beside it
        height, chosen = shadow_height(evidence, options)

        @functools.cache
        def dark() -> Any:
            steps, gap = options["time_steps"], min_gap_us(options["min_gap_ms"], evidence.refractory_us, 1.0)
            if devices.on_host(evidence.device):
                return event_darkness(evidence, steps, gap)
            import torch  # deferred: only a solver on a device sweeps there

            # the same map at every detection of a solve: moved to the device once
            return evidence.of_capture(("fused_dark", steps, gap), lambda: torch.as_tensor(
                event_darkness(evidence, steps, gap), device=evidence.device))

        # the same surface told only that inter-reflection is taken out confirms the same shadows at its own height
        key = ("fused_confirmed", evidence.fitted, *sorted((k, v) for k, v in options.items() if k != "reflected_scale"))
        shadows, seen = evidence.of_surface(key, lambda: _confirmed(evidence, options, height, dark()))
        chosen = {**chosen, **seen}
        if evidence.inter_reflected and options["reflected_scale"] > 1.0:
            taller, _ = _confirmed(evidence, options, height * np.float32(options["reflected_scale"]), dark())
            # the table merges what overlaps or touches: the union
            shadows = ShadowIntervals.concatenate([shadows, taller])
        return replace(evidence.frame_mask(shadows), diagnostics=chosen)


def _confirmed(evidence: ShadowEvidence, options: dict[str, Any], height: np.ndarray, dark: Any
               ) -> tuple[ShadowIntervals, dict[str, int]]:
    """The shadows of the surface of ``height`` that the events confirm (module docstring), keyed by flat
    frame pixel, and the record of the edges seen (empty when the options take none). ``dark``:
    ``event_darkness`` on the options' time grid, a tensor on the evidence's device where that is not
    the host."""
    steps = options["time_steps"]
    pixels = np.flatnonzero(np.asarray(evidence.mask).ravel())
    covering = evidence.super_pixel[pixels]
    confirmed = run_collector(pixels.size, evidence.device)
    edge_share = options["fitted_edge_share" if evidence.fitted else "edge_share"]
    edges = edge_share > 0
    if edges:
        tracker = edge_tracker(SuperPixels.shared(evidence), evidence.device, count_pixels=True)
        surface = run_collector(pixels.size, evidence.device)
    under = _dark_columns(dark, covering, evidence.device)
    start = 0
    # one sweep, a block of times at a time: no (steps, P) map of the surface's shadows is ever whole
    for block in surface_shadow_blocks(evidence, height, steps, options["margin_px"]):
        if edges:
            tracker.feed(block)
            surface.feed(block)
        confirmed.feed(block & under(start, len(block)))
        start += len(block)
    shadows = confirmed.intervals(evidence.period_us, pixels)
    if not edges:
        return shadows, {}
    seen = seen_edges(evidence, tracker, options["edge_tolerance_deg"])
    extra = _seen_at_pixels(evidence, seen, surface, pixels, edge_share)
    # the table merges what overlaps or touches: the union of both kinds of confirmation
    return ShadowIntervals.concatenate([shadows, extra]), seen.record()


def _dark_columns(dark: Any, covering: np.ndarray, device: str) -> Callable[[int, int], Any]:
    """``at(start, n)``: (n, P) bool, the rows ``start``… of ``dark`` (steps, He·We) at the super pixels
    ``covering`` (P,) the masked frame pixels, where ``surface_shadow_blocks`` gives its blocks on
    ``device`` (``dark`` a tensor there)."""
    if devices.on_host(device):
        # np.take gathers a block's columns 5× faster than indexing with an index array
        return lambda start, n: np.take(dark[start : start + n], covering, axis=1)
    import torch  # deferred: only a solver on a device sweeps there

    columns = torch.as_tensor(covering, device=device)
    return lambda start, n: dark[start : start + n].index_select(1, columns)


def _seen_at_pixels(evidence: ShadowEvidence, seen: SeenShadows, surface: RunCollector | DeviceRunCollector,
                    pixels: np.ndarray, edge_share: float) -> ShadowIntervals:
    """The surface's shadows where the events saw their super pixel's edges, at the frame pixels the
    surface shadows for at most ``edge_share`` of the period. ``surface``: the surface's shadows of the
    masked frame pixels ``pixels`` (P,), a column each, on the time grid of ``seen``; the result is keyed
    by flat pixel. On the host worked through SEEN_CHUNK pixels at a time; on a device
    (``_seen_there``) as many as its memory takes."""
    covering = evidence.super_pixel[pixels]
    column = np.full(evidence.event_shape[0] * evidence.event_shape[1], -1, dtype=np.int64)
    column[seen.columns] = np.arange(seen.columns.size)
    taking = np.flatnonzero((column[covering] >= 0) & (seen.pixel_share <= edge_share))
    if isinstance(surface, DeviceRunCollector):
        return _seen_there(surface, seen.seen, column[covering[taking]], taking, pixels, evidence.period_us)
    steps = seen.seen.shape[0]
    shadows = surface.intervals(evidence.period_us)
    keep = np.isin(shadows.pixel, taking)
    owner, t0, t1 = shadows.pixel[keep], shadows.t0_us[keep], shadows.t1_us[keep]
    parts = []
    for first in range(0, taking.size, SEEN_CHUNK):
        part = taking[first : first + SEEN_CHUNK]
        inside = (owner >= part[0]) & (owner <= part[-1])
        local = np.searchsorted(part, owner[inside])
        grid = rasterize(ShadowIntervals(local, t0[inside], t1[inside]), part.size, evidence.period_us, steps)
        grid &= np.take(seen.seen, column[covering[part]], axis=1)
        parts.append(intervals_from_grid(grid, evidence.period_us, pixels[part]))
    return ShadowIntervals.concatenate(parts)


def _seen_there(surface: DeviceRunCollector, seen: np.ndarray, seen_column: np.ndarray, taking: np.ndarray,
                pixels: np.ndarray, period_us: float) -> ShadowIntervals:
    """``_seen_at_pixels`` on the device of ``surface``: the surface's shadows at the columns ``taking``
    (T,) rebuilt there from its runs (``DeviceRunCollector.grid_at``), and with the seen map ``seen``
    (steps, C) at their columns ``seen_column`` (T,), their runs found there; the same intervals as the
    host's, which rasterizes the runs read back."""
    import torch  # deferred: only a solver on a device sweeps there

    device = surface.previous.device
    seen_there = torch.as_tensor(seen, device=device)
    # a column's bytes at a time: the ±1 table, its running sum, the grid, the seen columns, the collector's
    chunk = max(1, devices.memory_budget(device, SEEN_BYTES) // (6 * (surface.rows + 1)))
    parts = []
    for first in range(0, taking.size, chunk):
        part = taking[first : first + chunk]
        grid = surface.grid_at(torch.as_tensor(part, device=device))
        grid &= seen_there.index_select(1, torch.as_tensor(seen_column[first : first + chunk], device=device))
        collector = DeviceRunCollector(part.size, device)
        collector.feed(grid)
        parts.append(collector.intervals(period_us, pixels[part]))
    return ShadowIntervals.concatenate(parts)
