"""Hand-made event streams for the shadow and preprocessing tests: one sensor row, pixels 0, 1, …"""

from __future__ import annotations

import numpy as np

import psfmt


def event_stream(rows: list[list[tuple[float, int]]]) -> psfmt.EventArray:
    """Events of pixels 0, 1, … (one row of the sensor) from (t_us, polarity) lists, sorted by time."""
    x = np.concatenate([np.full(len(r), i) for i, r in enumerate(rows)])
    t = np.concatenate([[e[0] for e in r] for r in rows]).astype(np.int64)
    p = np.concatenate([[e[1] for e in r] for r in rows])
    order = np.argsort(t, kind="stable")
    return psfmt.EventArray(x[order], np.zeros(len(t)), t[order], p[order])


def shading(t0: float, t1: float, step: float, polarity: int) -> list[tuple[float, int]]:
    """Slow shading events every ``step`` µs in [t0, t1): |f| = C/step, far below θ."""
    return [(t, polarity) for t in np.arange(t0, t1, step)]
