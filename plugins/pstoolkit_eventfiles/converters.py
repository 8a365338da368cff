"""The ``raw`` and ``dsec`` converters: event recordings → hybrid captures, in bounded memory.

Events stream from the decoder into ``psfmt.CaptureWriter`` block by block. A capture's events are
sorted; the few that a sensor stamps earlier than their predecessor (small backward TIME_LOW steps,
which EVT 3.0 decoders keep as they are) get their predecessor's time and are counted. Whatever was
skipped, dropped or re-timed is logged as one warning line; a clean recording logs nothing. A
recording that leaves no event (a header alone, every event outside the sensor) is refused unless
``--allow-empty`` asks for the empty capture.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

import psfmt
import pstoolkit
from psfmt.atomic import temporary_sibling
from psfmt.dsec import DEFAULT_CHUNK_EVENTS, DsecFile
from psfmt.evt2 import Evt2File
from psfmt.evt3 import Evt3File
from psfmt.limits import MAX_SENSOR_SIDE
from psfmt.rawheader import concat_triggers, read_header
from pstoolkit import Converter, Option, Progress, UserError
from pstoolkit_eventfiles.attach import (
    ATTACH_OPTIONS,
    load_calibration,
    load_frames,
    load_lights,
    time_frames,
    write_attachments,
)

log = logging.getLogger("pstoolkit.eventfiles")


class Monotone:
    """Clamps each event time to the latest time seen so far, counting the events it moved."""

    def __init__(self) -> None:
        self.last_us = np.iinfo(np.int64).min
        self.moved = 0

    def __call__(self, events: psfmt.EventArray) -> psfmt.EventArray:
        if len(events) == 0:
            return events
        t = np.maximum.accumulate(np.maximum(events.t, self.last_us))
        moved = int(np.count_nonzero(t != events.t))
        self.last_us = int(t[-1])
        if moved:
            self.moved += moved
            return psfmt.EventArray(events.x, events.y, t, events.p)
        return events


def open_raw(src: Path) -> Evt3File | Evt2File:
    """The EVT 3.0 or EVT 2.0 reader that the RAW header asks for."""
    header = read_header(src)
    if header.encoding == "EVT3":
        return Evt3File(src)
    if header.encoding == "EVT2":
        return Evt2File(src)
    if header.encoding is None:
        raise UserError(f"{src}: no '% evt' or '% format' header line: not a Prophesee RAW file")
    raise UserError(f"{src}: {header.encoding} RAW files are not supported (EVT 3.0 and EVT 2.0 are)")


ALLOW_EMPTY = Option("allow_empty", bool, False, "write the capture even when the recording leaves no event")


class _EventFile(Converter):
    """Shared by the event-file converters: attachments checked first, then events streamed."""

    options: ClassVar[tuple[Option, ...]] = (*ATTACH_OPTIONS, ALLOW_EMPTY)

    def convert(self, src: Path, out: Path, options: dict[str, Any], progress: Progress) -> list[Path]:
        if src.is_dir():
            raise UserError(f"{src}: is a folder, expected a {self.name} file")
        frames = load_frames(options["frames"])
        lights = load_lights(options["lights"])
        calibration = load_calibration(options["calibration"])
        description = f"{src.name} converted by pstoolkit convert {self.name}"
        # written beside OUT and validated before the rename, so a bad light model or calibration
        # from the user's files never leaves a capture that pstoolkit cannot read
        staging = temporary_sibling(out)
        try:
            with psfmt.CaptureWriter(staging, description=description, creator="pstoolkit", creator_version=pstoolkit.__version__) as writer:
                triggers, notes = self.write_events(src, writer, options, progress)
                if writer.event_count == 0 and not options["allow_empty"]:
                    why = f" ({notes})" if notes else ""
                    raise UserError(f"{src}: no events to convert{why}; --allow-empty writes the empty capture anyway")
                if len(triggers):
                    writer.set_triggers(triggers.t, triggers.channel, triggers.value)
                if frames is not None and not (frames.has_windows or frames.has_instant_lights):
                    time_frames(frames, triggers, options["trigger_channel"], Path(options["frames"]))
                write_attachments(writer, frames, lights, calibration)
            report = psfmt.validate(staging)
            if report.errors:
                raise UserError(f"{out}: not written: {report.errors[0].text}")
            os.replace(staging, out)
        finally:
            staging.unlink(missing_ok=True)
        if notes:
            log.warning("%s: %s", src, notes)
        return [out]

    def write_events(
        self, src: Path, writer: psfmt.CaptureWriter, options: dict[str, Any], progress: Progress
    ) -> tuple[psfmt.Triggers, str]:
        """Stream the events of ``src`` into ``writer``; return the triggers and a note on anything
        skipped ("" when nothing was)."""
        raise NotImplementedError


class Raw(_EventFile):
    name = "raw"
    summary = "Prophesee RAW recordings (EVT 3.0 or EVT 2.0), with frames, light model and calibration"

    def write_events(
        self, src: Path, writer: psfmt.CaptureWriter, options: dict[str, Any], progress: Progress
    ) -> tuple[psfmt.Triggers, str]:
        reader = open_raw(src)
        writer.begin_events(reader.width, reader.height)
        total = max(1, src.stat().st_size - reader.header.data_offset)
        step = reader.chunk_words * (2 if isinstance(reader, Evt3File) else 4)
        monotone = Monotone()
        triggers = []
        for k, (events, trig) in enumerate(reader.chunks()):
            writer.append_events(monotone(events))
            triggers.append(trig)
            progress(min(1.0, (k + 1) * step / total), "events")
        notes = [] if reader.stats.clean else [reader.stats.summary()]
        if monotone.moved:
            notes.append(f"{monotone.moved:,} events stamped before their predecessor got its time")
        return concat_triggers(triggers), "; ".join(notes)


class Dsec(_EventFile):
    name = "dsec"
    summary = "DSEC-style event HDF5 (/events/{x,y,p,t}, /t_offset, /ms_to_idx)"
    options = (
        Option("width", int, 0, "sensor width in pixels (0: the file's width attribute, else the largest x + 1)", minimum=0),
        Option("height", int, 0, "sensor height in pixels (0: the file's height attribute, else the largest y + 1)", minimum=0),
        *ATTACH_OPTIONS,
        ALLOW_EMPTY,
    )

    def write_events(
        self, src: Path, writer: psfmt.CaptureWriter, options: dict[str, Any], progress: Progress
    ) -> tuple[psfmt.Triggers, str]:
        with DsecFile(src) as dsec:
            width, height = options["width"] or dsec.width, options["height"] or dsec.height
            if width is None or height is None:
                extent = dsec.extent()
                width, height = width or extent[0], height or extent[1]
                if max(width, height) > MAX_SENSOR_SIDE:
                    raise UserError(
                        f"{src}: coordinates reach x = {width - 1}, y = {height - 1}, beyond the {MAX_SENSOR_SIDE} pixels a side "
                        "of an event sensor; give --width and --height to keep the events inside them"
                    )
            writer.begin_events(width, height)
            outside = 0
            for k, block in enumerate(dsec.chunks()):
                if len(block) and not block.is_sorted():
                    raise UserError(f"{src}: /events/t is not sorted (block {k})")
                inside = (block.x < width) & (block.y < height)
                outside += int(len(block) - np.count_nonzero(inside))
                writer.append_events(block if inside.all() else block[inside])
                progress(min(1.0, (k + 1) * DEFAULT_CHUNK_EVENTS / max(1, dsec.count)), "events")
            # events with x or y beyond uint16 were dropped while reading: outside any sensor
            outside += dsec.beyond
        note = f"{outside:,} events outside {width}×{height} dropped" if outside else ""
        return concat_triggers([]), note
