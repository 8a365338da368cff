"""Storage checks, before anything of a dataset is read: what a file declares against what it stores.

A declared shape is only a claim, and links, virtual or external datasets and unknown filters would
read other files or inflate without bound; each is refused here, so the checks after it can read.
"""

from __future__ import annotations

from typing import Any

import h5py

from psfmt import layout
from psfmt._validate.findings import Findings
from psfmt._validate.values import element_count
from psfmt.events import EVENT_DTYPES
from psfmt.limits import DEFLATE_MAX_RATIO, FILL_ALLOWANCE, MAX_SMALL_CHUNKS, SMALL_CHUNK_BYTES, Limits
from psfmt.version import FORMAT_VERSION_STR

ALLOWED_FILTERS = {1: "deflate", 2: "shuffle", 3: "fletcher32"}
KNOWN_GROUPS = (
    layout.FRAMES,
    layout.EVENTS,
    layout.TRIGGERS,
    layout.LIGHTS,
    layout.CALIBRATION,
    layout.GROUND_TRUTH,
    layout.RESULTS,
)


def check_dataset(where: str, ds: h5py.Dataset, file_bytes: int, limits: Limits, out: Findings, *, whole: bool = True) -> None:
    """A dataset's storage before any of it is read: no virtual or external data (other files), only
    the format's filters, numbers, and a declared size the stored bytes can hold (at most
    ``DEFLATE_MAX_RATIO`` times them once inflated) within the limits. ``whole``: a reader reads the
    dataset at once, so it must fit ``limits.max_array_bytes``."""
    plist = ds.id.get_create_plist()
    if plist.get_layout() == h5py.h5d.VIRTUAL:
        out.error(where, "is a virtual dataset: its data would come from other files, which a capture must not refer to")
        return
    if plist.get_external_count():
        out.error(where, "keeps its data in external files, which a capture must not refer to")
        return
    codes = [int(plist.get_filter(i)[0]) for i in range(plist.get_nfilters())]
    other = [c for c in codes if c not in ALLOWED_FILTERS]
    if other:
        out.error(where, f"uses HDF5 filter {other[0]}; format {FORMAT_VERSION_STR} allows only deflate (1), shuffle (2) and fletcher32 (3)")
        return
    if ds.shape is None or ds.dtype.kind not in "biuf":
        out.error(where, f"has dtype {ds.dtype}{'' if ds.shape is not None else ' and no dataspace'}, expected numbers")
        return
    itemsize = ds.dtype.itemsize
    declared = element_count(ds.shape) * itemsize
    if ds.chunks is not None and element_count(ds.chunks) * itemsize > limits.max_chunk_bytes:
        out.error(where, f"has chunks of {element_count(ds.chunks) * itemsize:,} bytes, more than the limit of {limits.max_chunk_bytes:,} "
                  "(PSFMT_MAX_CHUNK_BYTES)")
        return
    if ds.chunks is not None and element_count(ds.chunks) * itemsize < SMALL_CHUNK_BYTES:
        count = element_count(tuple(-(-n // c) for n, c in zip(ds.shape, ds.chunks)))
        if count > MAX_SMALL_CHUNKS:
            out.error(where, f"is cut into {count:,} chunks of {element_count(ds.chunks) * itemsize:,} bytes; at most {MAX_SMALL_CHUNKS:,} "
                      f"chunks under {SMALL_CHUNK_BYTES:,} bytes are read (HDF5 spends kilobytes of memory on each chunk it reads)")
            return
    stored = int(ds.id.get_storage_size())
    if stored > file_bytes:
        out.error(where, f"claims {stored:,} bytes of storage in a file of {file_bytes:,} bytes (a damaged file)")
        return
    most = stored * (DEFLATE_MAX_RATIO if 1 in codes else 1)
    if declared > max(FILL_ALLOWANCE, most):
        held = f"stores {stored:,} bytes for it, which inflate to at most {most:,}" if stored else "stores no data for it"
        out.error(where, f"declares {ds.shape} {ds.dtype} ({declared:,} bytes) but the file {held}")
        return
    if whole and declared > limits.max_array_bytes:
        out.error(where, f"holds {declared:,} bytes, more than the limit of {limits.max_array_bytes:,} read at once (PSFMT_MAX_ARRAY_BYTES)")


def member(group: h5py.Group, name: str, where: str, out: Findings) -> Any:
    """The object ``group[name]`` (None when absent); an external link is reported, not followed."""
    link = group.get(name, getlink=True)
    if link is None:
        return None
    if isinstance(link, h5py.ExternalLink):
        out.error(where, "is an external link to another file, which a capture must not refer to")
        return None
    return group[name]


def check_storage(f: h5py.File, file_bytes: int, limits: Limits, out: Findings) -> None:
    """Every group and dataset a reader may open, before anything of them is read (see ``check_dataset``)."""
    for name in KNOWN_GROUPS:
        where = f"/{name}"
        group = member(f, name, where, out)
        if group is None:
            continue
        if not isinstance(group, h5py.Group):
            out.error(where, "must be a group")
            continue
        for key in group:
            path = f"{where}/{key}"
            obj = member(group, key, path, out)
            if name == layout.RESULTS or (name == layout.GROUND_TRUTH and key == layout.MATERIALS):
                if obj is not None and not isinstance(obj, h5py.Group):
                    out.error(path, "must be a group")
                elif obj is not None:
                    for inner in obj:
                        item = member(obj, inner, f"{path}/{inner}", out)
                        if isinstance(item, h5py.Dataset):
                            check_dataset(f"{path}/{inner}", item, file_bytes, limits, out)
            elif isinstance(obj, h5py.Dataset):
                streamed = (name == layout.EVENTS and key in EVENT_DTYPES) or (name == layout.FRAMES and key == "data")
                check_dataset(path, obj, file_bytes, limits, out, whole=not streamed)
