"""Checks of single values that every group of a capture shares: numbers, times, image sizes."""

from __future__ import annotations

import math
from typing import Any

import h5py

from psfmt._validate.findings import Findings
from psfmt.limits import MAX_ABS_TIME_US, Limits


def is_int(value: Any) -> bool:
    """Whether ``value`` (a plain attribute value) is an integer; a bool is not."""
    return isinstance(value, int) and not isinstance(value, bool)


def is_number(value: Any) -> bool:
    """Whether ``value`` (a plain attribute value) is a finite int or float; a bool is not."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def dataset(group: h5py.Group, key: str) -> h5py.Dataset | None:
    """``group[key]`` when it is a dataset; None when it is absent or something else."""
    obj = group.get(key)
    return obj if isinstance(obj, h5py.Dataset) else None


def element_count(shape: tuple[int, ...]) -> int:
    """Elements of an array of ``shape`` (1 for a scalar), as a Python int that cannot overflow."""
    return math.prod(int(d) for d in shape)


def check_pixels(where: str, height: int, width: int, limits: Limits, out: Findings) -> bool:
    """Whether an image of ``height`` × ``width`` pixels is within ``limits.max_pixels``; an error when not."""
    if height * width > limits.max_pixels:
        out.error(where, f"is {width}×{height} pixels, more than the limit of {limits.max_pixels:,} (PSFMT_MAX_PIXELS)")
        return False
    return True


def check_time(where: str, value: Any, out: Findings, what: str = "time") -> bool:
    """Whether a time in µs is within ±2⁵³ µs (``MAX_ABS_TIME_US``); an error naming ``what`` when not."""
    if abs(value) > MAX_ABS_TIME_US:
        out.error(where, f"{what} {value} µs lies beyond ±2^53 µs (±285 years), where times stop converting to float64 exactly")
        return False
    return True
