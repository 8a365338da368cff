"""The shadow-detector contract: what a detector sees (``ShadowEvidence``), what it returns
(``ShadowMask``, the cast-shadow mask m_c(x, t) of DualResPS eq. 14 at frame pixels) and the base
class registered through ``pstoolkit_register_shadow_detectors``.

    class Mine(ShadowDetector):
        name = "mine"
        summary = "pixels whose events fall silent for longer than a threshold"
        options = (Option("threshold_ms", float, 5.0, "shortest silence"),)

        def detect(self, evidence, options):
            intervals = ...                        # ShadowIntervals at event pixels, phases
            return evidence.event_mask(intervals)

A solver builds the evidence once per capture and calls ``detect`` again whenever it has a better
surface estimate (``evidence.normal``) if the detector sets ``uses_surface``.
"""

from __future__ import annotations

import hashlib
from abc import ABC, abstractmethod
from collections.abc import Callable, Hashable
from dataclasses import dataclass, field, replace
from typing import Any, ClassVar, TypeVar

import numpy as np

from pstoolkit.optics.lights import LightModel
from pstoolkit.plugin.options import Option
from pstoolkit.shadows.intervals import ShadowIntervals, ShadowTable
from pstoolkit.shadows.period_profile import Profile

T = TypeVar("T")
# The key under which ShadowEvidence.memo holds the digest of the surface its values were computed from.
_SURFACE = object()


@dataclass
class ShadowMask:
    """When each frame pixel is in a cast shadow: intervals of the light's phase in ``table``, keyed
    by ``cell`` (H·W,) int64 — the frame pixel's own index for a frame-resolution mask, or the event
    pixel covering it for an event-resolution one. Times are absolute µs; the phase origin is
    ``t0_us`` and the light repeats every ``table.period_us``. ``diagnostics``: what the detector
    chose on the way, JSON-ready (the ``geometry`` detectors' height scale), for a solver to record."""

    table: ShadowTable
    cell: np.ndarray
    t0_us: float
    diagnostics: dict[str, Any] = field(default_factory=dict)

    @property
    def period_us(self) -> float:
        return self.table.period_us

    def __len__(self) -> int:
        """Merged intervals in the table (0: no pixel is ever in shadow)."""
        return len(self.table)

    @classmethod
    def from_intervals(cls, intervals: ShadowIntervals, cell: np.ndarray, t0_us: float, period_us: float) -> ShadowMask:
        return cls(ShadowTable.build(intervals, period_us), np.asarray(cell, dtype=np.int64), float(t0_us))

    @classmethod
    def none(cls, n_pixels: int, t0_us: float, period_us: float) -> ShadowMask:
        """The mask of no shadow at all for ``n_pixels`` frame pixels."""
        return cls.from_intervals(ShadowIntervals.empty(), np.arange(n_pixels), t0_us, period_us)

    def contains(self, frame_pixel: np.ndarray, t_us: np.ndarray) -> np.ndarray:
        """(N,) bool: frame pixel ``frame_pixel`` (N,) (flat v·W + u) is in shadow at time ``t_us`` (N,)."""
        cell = self.cell[np.asarray(frame_pixel, dtype=np.int64)]
        return self.table.contains(cell, np.asarray(t_us, dtype=np.float64) - self.t0_us)

    def shadowed_us(self, frame_pixel: np.ndarray, t0_us: np.ndarray, t1_us: np.ndarray) -> np.ndarray:
        """(N,) µs frame pixel ``frame_pixel`` (N,) spends in shadow between times ``t0_us`` ≤ ``t1_us``
        (at most one period apart)."""
        cell = self.cell[np.asarray(frame_pixel, dtype=np.int64)]
        t0 = np.asarray(t0_us, dtype=np.float64) - self.t0_us
        return self.table.shadowed_us(cell, t0, t0 + (np.asarray(t1_us, dtype=np.float64) - np.asarray(t0_us, dtype=np.float64)))

    def contains_grid(self, frame_pixel: np.ndarray, t_us: np.ndarray) -> np.ndarray:
        """(T, N) bool: ``contains`` for every frame pixel (N,) at every time ``t_us`` (T,)."""
        cell = self.cell[np.asarray(frame_pixel, dtype=np.int64)]
        return self.table.contains_grid(cell, np.asarray(t_us, dtype=np.float64) - self.t0_us)

    def shadowed_grid(self, frame_pixel: np.ndarray, t0_us: np.ndarray, t1_us: np.ndarray) -> np.ndarray:
        """(T, N) µs: ``shadowed_us`` for every frame pixel (N,) in every window ``t0_us`` ≤ ``t1_us``
        (T,), each at most one period long."""
        cell = self.cell[np.asarray(frame_pixel, dtype=np.int64)]
        t0 = np.asarray(t0_us, dtype=np.float64)
        return self.table.shadowed_grid(cell, t0 - self.t0_us, np.asarray(t1_us, dtype=np.float64) - self.t0_us)

    def coverage(self) -> np.ndarray:
        """(H·W,) share of the period each frame pixel spends in shadow."""
        return self.table.coverage(int(self.cell.max()) + 1 if self.cell.size else 0)[self.cell]


@dataclass
class ShadowEvidence:
    """What a shadow detector may look at, for one capture.

    Geometry: ``frame_shape`` (H, W) and ``event_shape`` (He, We); ``super_pixel`` (H·W,) the event
    pixel nearest each frame pixel (through the calibrated event→frame affine); ``mask`` (H, W) the
    frame pixels on the object. Light: ``light`` (directional and periodic), ``t0_us`` the phase
    origin (the first exposure's start), ``period_us``. Sensor: ``contrast_pos``/``contrast_neg``
    (log units), ``refractory_us`` and ``refractory_rule`` (``pstoolkit.events.rule``). Data:
    ``profile`` the events of one period from ``t0_us`` at the event pixels (eq. 20);
    ``frames`` (J, H, W, 3) the mean frame of each of the period's exposure windows ``windows_us``
    (J, 2) phases, in units of saturation. Surface: ``normal`` (H, W, 3) the current estimate of
    the solver, None before it has one; ``fitted``: that estimate is a fit to these measurements
    (a re-detection), not a start such as a closed form; ``inter_reflected``: the solver takes light
    inter-reflected by the object out of these measurements (and its surface may have been flattened
    by it). ``device``: the torch device the solver computes on, where a detector may compute too (the
    surface's integration and sweep do, ``surface_sweep``). ``memo``: shared by the evidence and its
    copies with another surface (``with_normal``; any other copy starts an empty one), where a detector
    keeps what it computed from the surface (``of_surface``), so a solver that asks again of the same
    surface (told something else of it) does not pay twice; ``kept``, shared the same way, what it
    computed from the capture alone (``of_capture``), for every surface."""

    frame_shape: tuple[int, int]
    event_shape: tuple[int, int]
    super_pixel: np.ndarray
    mask: np.ndarray
    light: LightModel
    t0_us: float
    period_us: float
    contrast_pos: float
    contrast_neg: float
    refractory_us: float
    refractory_rule: str
    profile: Profile
    frames: np.ndarray
    windows_us: np.ndarray
    normal: np.ndarray | None = None
    fitted: bool = False
    inter_reflected: bool = False
    device: str = "cpu"
    memo: dict[Hashable, Any] = field(default_factory=dict, init=False, repr=False, compare=False)
    kept: dict[Hashable, Any] = field(default_factory=dict, init=False, repr=False, compare=False)

    def with_normal(self, normal: np.ndarray, fitted: bool = False, inter_reflected: bool = False) -> ShadowEvidence:
        """The same evidence with the surface estimate ``normal`` (H, W, 3), ``fitted`` to the
        measurements or a start, ``inter_reflected`` light taken out or not."""
        copy = replace(self, normal=np.asarray(normal, dtype=np.float32), fitted=fitted, inter_reflected=inter_reflected)
        copy.memo, copy.kept = self.memo, self.kept
        return copy

    def of_surface(self, key: Hashable, compute: Callable[[], T]) -> T:
        """``compute()``, a value computed from ``normal``, once per ``key`` (which names the options it
        used) for this evidence and its copies while they ask of the same surface (a digest of its
        bytes); a value asked of another surface drops those of the last, since a solver does not go
        back to an earlier surface. The value is shared: whoever takes it must not change it."""
        surface = None if self.normal is None else hashlib.blake2b(np.ascontiguousarray(self.normal).data, digest_size=16).digest()
        if self.memo.get(_SURFACE) != surface:
            self.memo.clear()
            self.memo[_SURFACE] = surface
        if key not in self.memo:
            self.memo[key] = compute()
        return self.memo[key]

    def of_capture(self, key: Hashable, compute: Callable[[], T]) -> T:
        """``compute()``, a value computed from the capture alone (not the surface), once per ``key``
        (which names the options it used) for this evidence and its copies, whatever surface they ask
        of. The value is shared: whoever takes it must not change it."""
        if key not in self.kept:
            self.kept[key] = compute()
        return self.kept[key]

    def forget(self) -> None:
        """Drop what ``of_surface`` keeps, for this evidence and its copies: a solver that will not ask
        of the last surface again frees it (a detector's sweeps keep tens of MB at 1024²)."""
        self.memo.clear()

    def event_mask(self, intervals: ShadowIntervals) -> ShadowMask:
        """A mask from intervals at event pixels: each frame pixel takes those of its super pixel."""
        return ShadowMask.from_intervals(intervals, self.super_pixel, self.t0_us, self.period_us)

    def frame_mask(self, intervals: ShadowIntervals) -> ShadowMask:
        """A mask from intervals at frame pixels (flat v·W + u)."""
        h, w = self.frame_shape
        return ShadowMask.from_intervals(intervals, np.arange(h * w), self.t0_us, self.period_us)

    def no_mask(self) -> ShadowMask:
        h, w = self.frame_shape
        return ShadowMask.none(h * w, self.t0_us, self.period_us)


class ShadowDetector(ABC):
    """A rule that finds cast shadows: ``name`` (registry name), ``summary`` (one line), typed
    ``options``; ``uses_surface`` True when ``detect`` uses ``evidence.normal``, so a solver calls it
    again as its estimate improves (with no estimate yet such a detector returns what it can, at
    worst ``evidence.no_mask()``)."""

    name: ClassVar[str]
    summary: ClassVar[str]
    options: ClassVar[tuple[Option, ...]] = ()
    uses_surface: ClassVar[bool] = False

    @abstractmethod
    def detect(self, evidence: ShadowEvidence, options: dict[str, Any]) -> ShadowMask:
        """The cast-shadow mask of the capture behind ``evidence``, with the full ``options`` dict
        (defaults filled in)."""


class NoShadows(ShadowDetector):
    """The ablation without a cast-shadow mask (supplement Table 2, "w/o m_c")."""

    name: ClassVar[str] = "none"
    summary: ClassVar[str] = "no cast-shadow mask: every observation counts as lit"

    def detect(self, evidence: ShadowEvidence, options: dict[str, Any]) -> ShadowMask:
        return evidence.no_mask()
