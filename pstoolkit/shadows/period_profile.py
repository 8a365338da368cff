"""The modified event interval profile of DualResPS (eq. 20) over one light period.

For event k of a super pixel, f_k = p_k·C^{p_k} / (t_k − t_{k−1}) in log units per second: large
positive where the irradiance rose fast (leaving a shadow), large negative where it fell fast
(entering one). The light is periodic, so a pixel's first event of the period takes the last one,
one period earlier, as its predecessor (the cyclic gap); a pixel with a single event gets the whole
period. Intervals are floored at 1 µs, the time resolution, so bursts in the same µs stay finite.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from psfmt import EventArray
from pstoolkit.optics.lights import US_PER_S

MIN_INTERVAL_US = 1.0


@dataclass
class Profile:
    """Profile samples of one period, grouped by super pixel, in time order within a pixel.

    ``pixel`` (N,) flat event pixel (y·width + x), ``t_us`` (N,) float64 phase in [0, period_us),
    ``p`` (N,) int8 polarity, ``f`` (N,) float64 log units per second, ``first`` (N,) index of the pixel's first sample,
    ``count`` (N,) the pixel's number of samples, ``period_us`` the light period.
    """

    pixel: np.ndarray
    t_us: np.ndarray
    p: np.ndarray
    f: np.ndarray
    first: np.ndarray
    count: np.ndarray
    period_us: float

    def __len__(self) -> int:
        return len(self.t_us)

    def neighbour(self, index: np.ndarray, offset: np.ndarray | int) -> np.ndarray:
        """The sample ``offset`` places after (negative: before) ``index`` in its pixel, cyclically."""
        local = index - self.first[index]
        return self.first[index] + np.mod(local + offset, self.count[index])

    def previous(self) -> tuple[np.ndarray, np.ndarray]:
        """Each sample's predecessor in its pixel (cyclically) and the time since it, µs: the whole
        period for a pixel's only sample."""
        previous = self.neighbour(np.arange(len(self)), -1)
        gap = np.where(self.count == 1, self.period_us, np.mod(self.t_us - self.t_us[previous], self.period_us))
        return previous, gap


def group_by_pixel(events: EventArray, width: int, t0_us: float, period_us: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Events of [t0_us, t0_us + period_us) as (pixel, phase µs float64, polarity), grouped by pixel
    and in time order within a pixel."""
    phase = events.t.astype(np.float64) - float(t0_us)
    keep = (phase >= 0) & (phase < period_us)
    pixel = events.y[keep].astype(np.int64) * width + events.x[keep].astype(np.int64)
    # a stable sort by pixel keeps each pixel's events in time order
    order = np.argsort(pixel, kind="stable")
    return pixel[order], phase[keep][order], events.p[keep][order].astype(np.int8)


def interval_profile(
    events: EventArray,
    width: int,
    *,
    t0_us: float,
    period_us: float,
    contrast_pos: float,
    contrast_neg: float,
) -> Profile:
    """Eq. 20 for the events of one period starting at ``t0_us``.

    Parameters
    ----------
    events
        The event stream, sorted by time; events outside [t0_us, t0_us + period_us) are ignored.
    width
        The sensor's width in pixels (pixel index y·width + x).
    t0_us, period_us
        Start of the period and the light period, µs.
    contrast_pos, contrast_neg
        Thresholds C⁺ and C⁻, log units.

    Returns
    -------
    Profile
        f_k in log units per second, with the phases, polarities and pixels of the events.
    """
    pixel, t, p = group_by_pixel(events, width, t0_us, period_us)
    n = len(t)
    starts = np.flatnonzero(np.r_[True, pixel[1:] != pixel[:-1]]) if n else np.empty(0, np.int64)
    sizes = np.diff(np.r_[starts, n])
    first = np.repeat(starts, sizes)
    count = np.repeat(sizes, sizes)
    local = np.arange(n) - first
    previous = first + np.mod(local - 1, np.maximum(count, 1))
    gap = np.mod(t - t[previous], period_us)
    # a lone event's predecessor is itself, one period earlier
    interval = np.where(count == 1, float(period_us), np.maximum(gap, MIN_INTERVAL_US))
    contrast = np.where(p > 0, contrast_pos, contrast_neg)
    f = p * contrast / (interval / US_PER_S)
    return Profile(pixel=pixel, t_us=t, p=p, f=f, first=first, count=count, period_us=float(period_us))
