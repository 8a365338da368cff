"""The ``raw``, ``dat``, ``hdf5`` (Metavision) and ``dsec`` converters: event recordings → hybrid captures, in bounded memory
(``aedat4`` in ``pstoolkit_eventfiles.aedat4`` builds on ``_EventFile`` here).

Events stream from the decoder into ``psfmt.CaptureWriter`` block by block. A capture's events are
sorted; the few that a sensor stamps earlier than their predecessor (small backward TIME_LOW steps,
which EVT 3.0 decoders keep as they are, or a DAT file's times going back) get their predecessor's
time and are counted. Whatever was skipped, dropped or re-timed is logged as one warning line; a
clean recording logs nothing. A recording that leaves no event (a header alone, every event outside
the sensor) is refused unless ``--allow-empty`` asks for the empty capture.

RAW, DAT and Metavision HDF5 files take their sensor size from the header as Metavision does
(``psfmt.eventfiles.rawheader.resolve_geometry``), or from ``--geometry WxH``; the capture's description records
where it came from (``geometry_source = …``) and keeps the file's header lines.
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
from psfmt.eventfiles.dat import DatFile
from psfmt.eventfiles.dsec import DEFAULT_CHUNK_EVENTS, DsecFile
from psfmt.eventfiles.evt2 import Evt2File
from psfmt.eventfiles.evt3 import Evt3File
from psfmt.eventfiles.metavision_hdf5 import MetavisionHdf5File
from psfmt.eventfiles.rawheader import RawHeader, concat_triggers, missing_geometry, parse_geometry, read_header
from psfmt.limits import MAX_SENSOR_SIDE
from psfmt.text import printable
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


GEOMETRY_HINT = "give the sensor size with --geometry WxH"
MAX_KEPT_LINES = 256
MAX_KEPT_CHARS = 16384


def geometry_option(text: str) -> tuple[int, int] | None:
    """The ``--geometry WxH`` override (None when not given); UserError for anything but ``WxH``."""
    if not text:
        return None
    geometry = parse_geometry(text)
    if geometry is None:
        raise UserError(f"option geometry: expected WxH (e.g. 1280x720), got {text!r}")
    return geometry


def _sized(src: Path, header: RawHeader) -> None:
    """UserError listing what was looked for when the header gives no sensor size."""
    if header.width is None or header.height is None:
        raise UserError(f"{src}: {missing_geometry(header)}; {GEOMETRY_HINT}")


def is_dat(src: Path, header: RawHeader) -> bool:
    """Whether ``src`` is a Metavision DAT file: a ``.dat`` name, or a DAT header (``% Data file
    containing …``) where no RAW encoding is declared."""
    return src.suffix.lower() == ".dat" or (header.encoding is None and header.fields.get("Data", "").startswith("file containing"))


def open_raw(src: Path, geometry: tuple[int, int] | None = None) -> Evt3File | Evt2File:
    """The EVT 3.0 or EVT 2.0 reader that the RAW header asks for (``geometry`` overriding its size)."""
    header = read_header(src, geometry=geometry)
    if header.encoding is None:
        raise UserError(f"{src}: no '% evt' or '% format' header line: not a Prophesee RAW file")
    if header.encoding not in ("EVT3", "EVT2"):
        raise UserError(f"{src}: {header.encoding} RAW files are not supported (EVT 3.0 and EVT 2.0 are)")
    _sized(src, header)
    return Evt3File(src, geometry=geometry) if header.encoding == "EVT3" else Evt2File(src, geometry=geometry)


def open_dat(src: Path, geometry: tuple[int, int] | None = None) -> DatFile:
    """The reader of a Metavision DAT file of CD events (``geometry`` overriding its size)."""
    header = read_header(src, label="DAT", geometry=geometry)
    if not header.lines:
        raise UserError(f"{src}: no '% ' header lines: not a Metavision DAT file")
    _sized(src, header)
    return DatFile(src, geometry=geometry)


def header_lines(header: RawHeader) -> list[str]:
    """The description lines that keep a file's header: where the geometry came from, then the
    header lines as written (made printable, at most ``MAX_KEPT_LINES`` lines and ``MAX_KEPT_CHARS``
    characters, so that an HDF5 attribute holds them)."""
    out = [f"geometry_source = {printable(header.geometry_source)}", f"{header.label.lower()}_header:"]
    kept = 0
    for k, line in enumerate(header.lines):
        text = printable(line)
        if k >= MAX_KEPT_LINES or kept + len(text) > MAX_KEPT_CHARS:
            out.append(f"% … {len(header.lines) - k} more header line(s) not kept")
            break
        out.append(text)
        kept += len(text)
    return out


GEOMETRY = Option("geometry", str, "", "sensor size WxH (e.g. 1280x720), overriding whatever the file's header says or implies")
ALLOW_EMPTY = Option("allow_empty", bool, False, "write the capture even when the recording leaves no event")


class _EventFile(Converter):
    """Shared by the event-file converters: attachments checked first, then events streamed."""

    options: ClassVar[tuple[Option, ...]] = (*ATTACH_OPTIONS, ALLOW_EMPTY)

    def convert(self, src: Path, out: Path, options: dict[str, Any], progress: Progress) -> list[Path]:
        if src.is_dir():
            raise UserError(f"{src}: is a folder, expected a {self.name} file")
        frames = load_frames(options.get("frames", ""))
        lights = load_lights(options["lights"])
        calibration = load_calibration(options["calibration"])
        description = "\n".join([f"{src.name} converted by pstoolkit convert {self.name}", *self.prepare(src, options)])
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
                write_attachments(writer, frames, lights, self.complete_calibration(calibration))
            report = psfmt.validate(staging)
            if report.errors:
                raise UserError(f"{out}: not written: {report.errors[0].text}")
            os.replace(staging, out)
        finally:
            staging.unlink(missing_ok=True)
        if notes:
            log.warning("%s: %s", src, notes)
        return [out]

    def prepare(self, src: Path, options: dict[str, Any]) -> list[str]:
        """Open ``src`` (refusing a file it cannot read before anything is written) and return the
        lines the capture's description gets beside the usual first one."""
        return []

    def write_events(
        self, src: Path, writer: psfmt.CaptureWriter, options: dict[str, Any], progress: Progress
    ) -> tuple[psfmt.Triggers, str]:
        """Stream the events of ``src`` into ``writer``; return the triggers and a note on anything
        skipped ("" when nothing was)."""
        raise NotImplementedError

    def complete_calibration(self, calibration: psfmt.Calibration | None) -> psfmt.Calibration | None:
        """The calibration written with the events (``--calibration``'s, completed with what the
        recording itself implies)."""
        return calibration


def _notes(stats_clean: bool, summary: str, monotone: Monotone) -> str:
    notes = [] if stats_clean else [summary]
    if monotone.moved:
        notes.append(f"{monotone.moved:,} events stamped before their predecessor got its time")
    return "; ".join(notes)


class Raw(_EventFile):
    name = "raw"
    summary = "Prophesee RAW recordings (EVT 3.0 or EVT 2.0; Metavision .dat too), with frames, light model and calibration"
    options = (GEOMETRY, *ATTACH_OPTIONS, ALLOW_EMPTY)

    def prepare(self, src: Path, options: dict[str, Any]) -> list[str]:
        geometry = geometry_option(options["geometry"])
        dat = src.suffix.lower() == ".dat" or is_dat(src, read_header(src, geometry=geometry))
        self.reader: Evt3File | Evt2File | DatFile = open_dat(src, geometry) if dat else open_raw(src, geometry)
        return header_lines(self.reader.header)

    def write_events(
        self, src: Path, writer: psfmt.CaptureWriter, options: dict[str, Any], progress: Progress
    ) -> tuple[psfmt.Triggers, str]:
        reader = self.reader
        if isinstance(reader, DatFile):
            return _write_dat(src, reader, writer, progress)
        writer.begin_events(reader.width, reader.height)
        total = max(1, src.stat().st_size - reader.header.data_offset)
        step = reader.chunk_words * (2 if isinstance(reader, Evt3File) else 4)
        monotone = Monotone()
        triggers = []
        for k, (events, trig) in enumerate(reader.chunks()):
            writer.append_events(monotone(events))
            triggers.append(trig)
            progress(min(1.0, (k + 1) * step / total), "events")
        return concat_triggers(triggers), _notes(reader.stats.clean, reader.stats.summary(), monotone)


def _write_dat(src: Path, reader: DatFile, writer: psfmt.CaptureWriter, progress: Progress) -> tuple[psfmt.Triggers, str]:
    writer.begin_events(reader.width, reader.height)
    total = max(1, src.stat().st_size - reader.data_offset)
    step = reader.chunk_records * 8
    monotone = Monotone()
    for k, events in enumerate(reader.chunks()):
        writer.append_events(monotone(events))
        progress(min(1.0, (k + 1) * step / total), "events")
    return concat_triggers([]), _notes(reader.stats.clean, reader.stats.summary(), monotone)


class Dat(_EventFile):
    name = "dat"
    summary = "Metavision DAT files of CD events, with frames, light model and calibration"
    options = (GEOMETRY, *ATTACH_OPTIONS, ALLOW_EMPTY)

    def prepare(self, src: Path, options: dict[str, Any]) -> list[str]:
        self.reader = open_dat(src, geometry_option(options["geometry"]))
        return header_lines(self.reader.header)

    def write_events(
        self, src: Path, writer: psfmt.CaptureWriter, options: dict[str, Any], progress: Progress
    ) -> tuple[psfmt.Triggers, str]:
        return _write_dat(src, self.reader, writer, progress)


class Hdf5(_EventFile):
    name = "hdf5"
    summary = "Metavision HDF5 recordings (/CD/events, ECF-compressed or not; /EXT_TRIGGER/events), with frames, light model and calibration"
    options = (GEOMETRY, *ATTACH_OPTIONS, ALLOW_EMPTY)

    def prepare(self, src: Path, options: dict[str, Any]) -> list[str]:
        with MetavisionHdf5File(src, geometry=geometry_option(options["geometry"])) as reader:
            self.header = reader.header
        return header_lines(self.header)

    def write_events(
        self, src: Path, writer: psfmt.CaptureWriter, options: dict[str, Any], progress: Progress
    ) -> tuple[psfmt.Triggers, str]:
        with MetavisionHdf5File(src, geometry=geometry_option(options["geometry"])) as reader:
            writer.begin_events(reader.width, reader.height)
            done = 0
            for events in reader.chunks():
                writer.append_events(events)
                done += len(events)
                progress(done / max(1, reader.count), "events")
            return reader.triggers(), ""


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
