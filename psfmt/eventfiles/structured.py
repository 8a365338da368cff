"""Event arrays as the Python event libraries hold them: tonic's structured array (x, y, t, p).

tonic uses ``x``/``y`` int16, ``t`` int64 µs and ``p`` bool (True for an ON event); ``from_structured``
takes that layout or ``EventArray.to_structured``'s (any integer widths, p as bool, 0/1 or ±1).
"""

from __future__ import annotations

import numpy as np

from psfmt.events import EventArray

TONIC_DTYPE = np.dtype([("x", "<i2"), ("y", "<i2"), ("t", "<i8"), ("p", "?")])


def to_tonic(events: EventArray) -> np.ndarray:
    """A tonic-compatible structured array (fields x, y, t, p) of ``events``."""
    out = np.empty(len(events), dtype=TONIC_DTYPE)
    out["x"], out["y"], out["t"] = events.x, events.y, events.t
    out["p"] = events.p > 0
    return out


def from_structured(array: np.ndarray) -> EventArray:
    """Events from a structured array with fields x, y, t (µs) and p; a missing field is a ValueError."""
    names = array.dtype.names or ()
    missing = [f for f in "xytp" if f not in names]
    if missing:
        raise ValueError(f"structured events lack field(s) {', '.join(missing)} (have {', '.join(names) or 'none'})")
    return EventArray(array["x"], array["y"], array["t"], np.where(array["p"].astype(np.int64) > 0, 1, -1))
