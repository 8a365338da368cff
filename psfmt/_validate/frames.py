"""Checks of ``/frames``: the frame stack, its sensor attributes and per-frame windows or lights."""

from __future__ import annotations

import h5py
import numpy as np

from psfmt import layout
from psfmt._validate.findings import Findings
from psfmt._validate.scan import Scan
from psfmt._validate.values import check_pixels, check_time, dataset, is_int, is_number
from psfmt.attributes import attr
from psfmt.limits import Limits
from psfmt.model import COLOR_ORDERS, FRAME_DTYPES

SATURATED_SHARE_WARNING = 0.05


def frame_shape(f: h5py.File) -> tuple[int, ...] | None:
    """(K, H, W, C) of the frame stack, None when the file holds no 4-D one."""
    ds = dataset(f[layout.FRAMES], "data") if layout.FRAMES in f else None
    return tuple(ds.shape) if ds is not None and ds.ndim == 4 else None


def check_frames(f: h5py.File, limits: Limits, out: Findings) -> None:
    """The structure of ``/frames``: data shape and dtype, sensor attributes, windows or lights."""
    g = f[layout.FRAMES]
    where = f"/{layout.FRAMES}"
    ds = dataset(g, "data")
    if ds is None:
        out.error(where, "dataset 'data' is missing")
        return
    if ds.ndim != 4:
        out.error(f"{where}/data", f"has shape {ds.shape}, expected (K, H, W, C)")
        return
    k, h, w, c = ds.shape
    if ds.dtype not in FRAME_DTYPES:
        out.error(f"{where}/data", f"has dtype {ds.dtype}, expected uint8, uint16 or float32")
    if k == 0:
        out.error(f"{where}/data", "holds no frames")
    elif check_pixels(f"{where}/data", h, w, limits, out) and h * w * c * ds.dtype.itemsize > limits.max_array_bytes:
        out.error(f"{where}/data", f"has frames of {h * w * c * ds.dtype.itemsize:,} bytes, more than the limit of {limits.max_array_bytes:,} "
                  "read at once (PSFMT_MAX_ARRAY_BYTES)")
    order = attr(g, "color_order")
    if order not in COLOR_ORDERS:
        out.error(where, f"color_order {order!r} is not one of {sorted(COLOR_ORDERS)}")
    elif COLOR_ORDERS[order] != c:
        out.error(where, f"color_order {order!r} does not fit {c} channels")
    saturation = attr(g, "saturation")
    if not is_number(saturation) or saturation <= 0:
        out.error(where, f"saturation {saturation!r} must be a positive number")
    bits = attr(g, "bit_depth")
    if not is_int(bits) or not 1 <= bits <= ds.dtype.itemsize * 8:
        out.error(where, f"bit_depth {bits!r} does not fit dtype {ds.dtype}")
    black = attr(g, "black_level")
    if black is not None and not is_number(black):
        out.error(where, f"black_level {black!r} must be a number")
    if attr(g, "response") != "linear":
        out.error(where, f"response {attr(g, 'response')!r} is not 'linear'")
    windows = [key for key in layout.FRAME_WINDOW if key in g]
    if len(windows) == 1:
        out.error(where, f"{windows[0]} is given without its partner")
    for key in layout.FRAME_WINDOW:
        if key in g:
            w = dataset(g, key)
            if w is None or w.shape != (k,) or w.dtype.kind not in "iu":
                shape, dtype = (w.shape, w.dtype) if w is not None else ("none", "none (not a dataset)")
                out.error(f"{where}/{key}", f"has shape {shape} and dtype {dtype}, expected ({k},) int64")
                return
    if len(windows) == 2:
        start, end = g["t_start_us"][()], g["t_end_us"][()]
        for key, times in (("t_start_us", start), ("t_end_us", end)):
            if times.size and not all(check_time(f"{where}/{key}", int(v), out) for v in (times.min(), times.max())):
                return
        bad = np.flatnonzero(end.astype(np.int64) <= start.astype(np.int64))
        if bad.size:
            out.error(where, f"exposure window of frame {bad[0]} ends before it starts")
    for key in layout.FRAME_INSTANT:
        if key in g:
            instant = dataset(g, key)
            if instant is None or instant.shape != (k, 3):
                out.error(f"{where}/{key}", f"has shape {instant.shape if instant is not None else 'none'}, expected ({k}, 3)")
    if "light_intensity" in g and "light_direction" not in g:
        out.error(where, "light_intensity is given without light_direction")
    if not windows and "light_direction" not in g:
        out.error(where, "frames need exposure windows (t_start_us, t_end_us) or per-frame light_direction")


def scan_frames(g: h5py.Group, scan: Scan, out: Findings) -> None:
    """The frame data of the group ``g``, block by block: finite values, and the share saturated."""
    ds = g["data"]
    saturation = float(attr(g, "saturation"))
    saturated = 0
    for index, block in scan.read(ds, "frames"):
        if ds.dtype.kind == "f" and not np.all(np.isfinite(block)):
            finite = np.isfinite(block.reshape(block.shape[0], -1)).all(axis=1)
            k = (index[0].start or 0) + int(np.flatnonzero(~finite)[0])
            out.error(f"/{layout.FRAMES}/data", f"frame {k} holds NaN or infinite values")
            return
        saturated += int(np.count_nonzero(block >= saturation))
    share = saturated / max(1, ds.size)
    if share > SATURATED_SHARE_WARNING:
        out.warn(f"/{layout.FRAMES}/data", f"{100 * share:.1f} % of the pixel values are saturated")
