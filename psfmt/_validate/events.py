"""Checks of ``/events`` and ``/triggers``: columns, sensor size, the millisecond index, time order."""

from __future__ import annotations

from typing import Any

import h5py
import numpy as np

from psfmt import layout
from psfmt._validate.findings import Findings
from psfmt._validate.frames import frame_shape
from psfmt._validate.scan import SCAN_CHUNK, Scan
from psfmt._validate.values import check_pixels, check_time, dataset, is_int
from psfmt.attributes import attr
from psfmt.events import EVENT_DTYPES, MsIndexBuilder, ms_index_length
from psfmt.limits import MAX_SENSOR_SIDE, Limits

TRIGGER_DTYPES: dict[str, np.dtype[Any]] = {"t": np.dtype(np.int64), "channel": np.dtype(np.uint8), "value": np.dtype(np.int8)}


def check_events(f: h5py.File, limits: Limits, out: Findings) -> None:
    """The structure of ``/events``: sensor size, the x, y, t, p columns and the index's shape."""
    g = f[layout.EVENTS]
    where = f"/{layout.EVENTS}"
    sides = {}
    for key in ("width", "height"):
        value = attr(g, key)
        if not is_int(value) or value <= 0:
            out.error(where, f"attribute {key!r} must be a positive integer, got {value!r}")
        elif value > MAX_SENSOR_SIDE:
            out.error(where, f"{key} {value} exceeds {MAX_SENSOR_SIDE}, the most uint16 coordinates address")
        else:
            sides[key] = value
    if len(sides) == 2:
        check_pixels(where, sides["height"], sides["width"], limits, out)
    lengths = set()
    columns_ok = True
    for c, dtype in EVENT_DTYPES.items():
        ds = dataset(g, c)
        if ds is None:
            out.error(where, f"dataset {c!r} is missing")
            columns_ok = False
            continue
        if ds.ndim != 1:
            out.error(f"{where}/{c}", f"has shape {ds.shape}, expected 1-D")
        if ds.dtype != dtype:
            out.error(f"{where}/{c}", f"has dtype {ds.dtype}, expected {dtype}")
        columns_ok = columns_ok and ds.ndim == 1 and ds.dtype == dtype
        lengths.add(ds.shape[0] if ds.ndim else -1)
    if len(lengths) > 1:
        out.error(where, f"columns x, y, t, p differ in length ({sorted(lengths)})")
        return
    index = dataset(g, "ms_to_idx")
    origin = attr(g, "ms_origin_us")
    if index is None or origin is None:
        out.error(where, "the millisecond index (ms_to_idx, ms_origin_us) is missing")
    elif not is_int(origin):
        out.error(where, f"ms_origin_us {origin!r} must be an integer")
    elif check_time(where, origin, out, "ms_origin_us") and columns_ok:
        n = lengths.pop()
        t = g["t"]
        first, last = (int(t[0]), int(t[n - 1])) if n > 0 else (None, None)
        if n > 0 and not (check_time(f"{where}/t", first, out) and check_time(f"{where}/t", last, out)):
            return
        expected = ms_index_length(first, last)
        if index.shape != (expected,):
            out.error(f"{where}/ms_to_idx", f"has shape {index.shape}, expected ({expected},) for the stored times")
        elif index.dtype.kind not in "iu":
            out.error(f"{where}/ms_to_idx", f"has dtype {index.dtype}, expected uint64")


def check_triggers(f: h5py.File, out: Findings) -> None:
    """The structure of ``/triggers``: the t, channel, value columns, one length."""
    g = f[layout.TRIGGERS]
    where = f"/{layout.TRIGGERS}"
    lengths = set()
    for c, dtype in TRIGGER_DTYPES.items():
        ds = dataset(g, c)
        if ds is None:
            out.error(where, f"dataset {c!r} is missing")
        elif ds.ndim != 1 or ds.dtype != dtype:
            out.error(f"{where}/{c}", f"has shape {ds.shape} and dtype {ds.dtype}, expected (M,) {dtype}")
        else:
            lengths.add(ds.shape[0])
    if len(lengths) > 1:
        out.error(where, f"columns t, channel, value differ in length ({sorted(lengths)})")


def check_ratio(f: h5py.File, out: Findings) -> None:
    """A warning when the frame and event resolutions are not one scale apart, between 1 and 16."""
    shape = frame_shape(f)
    g = f.get(layout.EVENTS)
    if shape is None or g is None:
        return
    w, h = attr(g, "width"), attr(g, "height")
    if not is_int(w) or not is_int(h) or w <= 0 or h <= 0:
        return
    rx, ry = shape[2] / w, shape[1] / h
    if not 0.99 <= rx <= 16 or abs(rx - ry) > 0.02 * rx:
        out.warn("/", f"unusual frame/event resolution ratio {rx:.2f}×{ry:.2f} (expected equal, between 1 and 16)")


def scan_events(g: h5py.Group, scan: Scan, out: Findings) -> None:
    """The events of the group ``g``, ``SCAN_CHUNK`` at a time: sorted times within range, polarity
    ±1, coordinates on the sensor, and the stored millisecond index equal to the one they make."""
    where = f"/{layout.EVENTS}"
    width, height = attr(g, "width"), attr(g, "height")
    n = g["t"].shape[0]
    stored = g["ms_to_idx"]
    builder = MsIndexBuilder()
    checked = 0
    index_ok = True
    previous = None
    for start in range(0, n, SCAN_CHUNK):
        stop = min(start + SCAN_CHUNK, n)
        t = g["t"][start:stop]
        steps = np.flatnonzero(np.diff(t) < 0)
        if steps.size or (previous is not None and t[0] < previous):
            at = start + int(steps[0]) + 1 if steps.size else start
            out.error(f"{where}/t", f"events are not sorted by time (event {at} goes back)")
            return
        if not (check_time(f"{where}/t", int(t[0]), out) and check_time(f"{where}/t", int(t[-1]), out)):
            return
        previous = int(t[-1])
        builder.add(t)
        p = g["p"][start:stop]
        bad = np.flatnonzero((p != 1) & (p != -1))
        if bad.size:
            out.error(f"{where}/p", f"polarity of event {start + int(bad[0])} is {int(p[bad[0]])}, not ±1")
            return
        for c, limit in (("x", width), ("y", height)):
            col = g[c][start:stop]
            bad = np.flatnonzero(col >= limit)
            if bad.size:
                out.error(f"{where}/{c}", f"event {start + int(bad[0])} has {c} = {int(col[bad[0]])}, outside the {width}×{height} sensor")
                return
        # the index entries this block made final, against the stored ones (the index is never whole)
        entries = builder.take()
        index_ok = index_ok and np.array_equal(stored[checked : checked + len(entries)], entries)
        checked += len(entries)
        scan.advance((stop - start) * 11, "events")
    rest = builder.finish()
    index_ok = index_ok and checked + len(rest) == stored.shape[0] and np.array_equal(stored[checked:], rest)
    if attr(g, "ms_origin_us") != builder.origin_us or not index_ok:
        out.error(f"{where}/ms_to_idx", "does not match the event times (rebuild the index)")


def scan_triggers(g: h5py.Group, scan: Scan, out: Findings) -> None:
    """The triggers of the group ``g``, block by block: times within range, every column readable."""
    for _, block in scan.read(g["t"], "triggers"):
        if block.size and not all(check_time(f"/{layout.TRIGGERS}/t", int(v), out) for v in (block.min(), block.max())):
            return
    for c in ("channel", "value"):
        for _ in scan.read(g[c], "triggers"):
            pass
