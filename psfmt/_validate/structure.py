"""The structure tier: metadata, shapes and storage alone, which is what the reader refuses a file on."""

from __future__ import annotations

import os

import h5py

from psfmt import layout
from psfmt._validate.calibration import check_calibration
from psfmt._validate.events import check_events, check_ratio, check_triggers
from psfmt._validate.findings import Finding, Findings
from psfmt._validate.frames import check_frames
from psfmt._validate.lights import check_lights
from psfmt._validate.maps import check_ground_truth, check_results
from psfmt._validate.storage import check_storage
from psfmt.attributes import attr, attrs
from psfmt.limits import Limits
from psfmt.version import FORMAT_NAME, FORMAT_VERSION, FORMAT_VERSION_STR, parse_version


def check_root(f: h5py.File, out: Findings) -> None:
    """The root attributes: a fatal finding unless the file is a capture of a readable major version."""
    fmt = attr(f, "format")
    if fmt != FORMAT_NAME:
        out.fatal("/", f"not a {FORMAT_NAME} file (root attribute 'format' is {fmt!r})")
        return
    text = attr(f, "format_version")
    try:
        version = parse_version(text)
    except (ValueError, TypeError):
        out.fatal("/", f"format_version {text!r} is not MAJOR.MINOR")
        return
    if version[0] > FORMAT_VERSION[0]:
        out.fatal("/", f"format_version {text} is newer than this reader supports ({FORMAT_VERSION[0]}.x); update psfmt")
    elif version[0] < FORMAT_VERSION[0]:
        out.fatal("/", f"format_version {text} predates {FORMAT_VERSION_STR} and is not supported")
    elif version[1] > FORMAT_VERSION[1]:
        out.warn("/", f"written by format {text}, newer than {FORMAT_VERSION_STR}: parts this reader does not know are ignored")
    # the reader takes every root attribute of the format: each is read here, so a damaged one shows now
    values = attrs(f, layout.ROOT_ATTRS)
    for key in ("creator", "created"):
        if key not in values:
            out.warn("/", f"root attribute {key!r} is missing")
    if layout.FRAMES not in f and layout.EVENTS not in f:
        out.error("/", "the capture holds neither frames nor events")


def structure_findings(f: h5py.File, limits: Limits | None = None) -> list[Finding]:
    """Findings from metadata, shapes and storage alone (cheap: no data scan). A file whose storage
    is unsound (see ``psfmt._validate.storage``) gets no further checks: they would read what it declares."""
    limits = limits or Limits.from_env()
    out = Findings()
    check_root(f, out)
    if out.failed:
        return list(out)
    check_storage(f, os.path.getsize(f.filename), limits, out)
    if out.failed:
        return list(out)
    checks = (
        (layout.FRAMES, lambda: check_frames(f, limits, out)),
        (layout.EVENTS, lambda: check_events(f, limits, out)),
        (layout.TRIGGERS, lambda: check_triggers(f, out)),
        (layout.LIGHTS, lambda: check_lights(f, out)),
    )
    for name, check in checks:
        if name in f:
            check()
    frames = f.get(layout.FRAMES)
    instant = isinstance(frames, h5py.Group) and "light_direction" in frames
    if layout.LIGHTS not in f and not instant:
        out.warn("/", "no light model: solvers cannot use this capture without one")
    check_calibration(f, out)
    check_ground_truth(f, limits, out)
    check_results(f, limits, out)
    check_ratio(f, out)
    return list(out)
