"""The content tier: every dataset a reader may read, read block by block in bounded memory."""

from __future__ import annotations

import h5py

from psfmt import layout
from psfmt._validate.events import scan_events, scan_triggers
from psfmt._validate.findings import Finding, Findings
from psfmt._validate.frames import scan_frames
from psfmt._validate.lights import scan_lights
from psfmt._validate.maps import scan_normals
from psfmt._validate.scan import Progress, Scan


def remaining(f: h5py.File) -> list[tuple[str, h5py.Dataset]]:
    """Every dataset a reader may read that the group scans do not: frame metadata, the light and
    calibration tables, the ground-truth maps and every map of every stored result."""
    found = []
    for name in (layout.FRAMES, layout.LIGHTS, layout.CALIBRATION, layout.GROUND_TRUTH, layout.RESULTS):
        group = f.get(name)
        if group is None:
            continue
        for key, obj in group.items():
            if isinstance(obj, h5py.Dataset) and not (name == layout.FRAMES and key == "data"):
                found.append((f"/{name}/{key}", obj))
            elif isinstance(obj, h5py.Group) and (name == layout.RESULTS or key == layout.MATERIALS):
                found += [(f"/{name}/{key}/{k}", ds) for k, ds in obj.items() if isinstance(ds, h5py.Dataset)]
    return found


def content_findings(f: h5py.File, progress: Progress | None = None) -> list[Finding]:
    """Findings from reading every dataset in bounded memory (assumes the structure is sound);
    ``progress`` hears the share of the bytes read."""
    out = Findings()
    events, frames, triggers = f.get(layout.EVENTS), f.get(layout.FRAMES), f.get(layout.TRIGGERS)
    rest = remaining(f)
    total = sum(ds.size * ds.dtype.itemsize for _, ds in rest)
    total += events["t"].shape[0] * 11 if events is not None else 0
    total += frames["data"].size * frames["data"].dtype.itemsize if frames is not None else 0
    total += triggers["t"].size * 10 if triggers is not None else 0
    scan = Scan(total, progress)
    if events is not None:
        scan_events(events, scan, out)
    if frames is not None:
        scan_frames(frames, scan, out)
    if triggers is not None:
        scan_triggers(triggers, scan, out)
    if layout.LIGHTS in f:
        scan_lights(f[layout.LIGHTS], out)
    for where, ds in rest:
        for _ in scan.read(ds, where):
            pass
    gt = f.get(layout.GROUND_TRUTH)
    if gt is not None and "normal" in gt and gt["normal"].ndim == 3:
        scan_normals(f"/{layout.GROUND_TRUTH}", gt, out)
    if progress is not None:
        progress(1.0, "done")
    return list(out)
