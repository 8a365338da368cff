"""HDF5 attributes as plain Python values: the one way the reader and the validator read them.

A damaged attribute raises h5py's error, never reads as absent: both callers turn that error into the
FormatError of a damaged file, so the reader and the validator agree on every attribute.
"""

from __future__ import annotations

from typing import Any

import numpy as np


def plain(value: Any) -> Any:
    """An HDF5 attribute value as plain Python (str, int, float, bool) or a numpy array; bytes are
    decoded as UTF-8 with undecodable bytes replaced."""
    if isinstance(value, bytes):
        return value.decode("utf-8", errors="replace")
    if isinstance(value, np.generic):
        return value.item()
    return value


def attr(obj: Any, key: str) -> Any:
    """Attribute ``key`` of the HDF5 object ``obj`` as a plain value, None when it is absent."""
    return plain(obj.attrs[key]) if key in obj.attrs else None


def attrs(obj: Any, keys: tuple[str, ...] | None = None) -> dict[str, Any]:
    """The attributes ``keys`` of ``obj`` that are present (every attribute when ``keys`` is None),
    as plain values by name."""
    if keys is None:
        return {key: plain(value) for key, value in obj.attrs.items()}
    values = {key: attr(obj, key) for key in keys}
    return {key: value for key, value in values.items() if value is not None}
