"""The ``aedat4`` converter: iniVation AEDAT4 recordings (DV, dv-processing) → hybrid captures.

The packets are decoded by the ``aedat`` package (Rust; extra ``aedat4``), one at a time in file
order, so memory stays bounded by one packet whatever the file's length: event packets stream into
``psfmt.CaptureWriter``, each frame is appended as it comes with its exposure window
(``exposure_begin_t`` … ``exposure_end_t``, µs) as the capture's long exposure, and the external
trigger edges become ``/triggers``. A DAVIS's frames and events come from the same pixels, so the
frames must have the event sensor's size and the capture gets the identity event→frame affine.

Before the decoder sees the file, its container is walked here (magic line, header, every packet's
size against the file's length and ``MAX_PACKET_BYTES``), so a cut or crafted file is refused in one
line naming it; ``aedat`` then answers for what is inside the packets (flatbuffers, compression).
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

import psfmt
from psfmt.eventfiles.rawheader import concat_triggers
from psfmt.limits import MAX_ABS_TIME_US
from psfmt.text import printable
from pstoolkit import Option, Progress, UserError
from pstoolkit_eventfiles.attach import ATTACH_OPTIONS
from pstoolkit_eventfiles.converters import ALLOW_EMPTY, Monotone, _EventFile, _notes

MAGIC = b"#!AER-DAT4.0\r\n"
MAX_HEADER_BYTES = 1 << 24
"""The header is a flatbuffer holding the recording's XML description: kilobytes in practice."""
MAX_PACKET_BYTES = 1 << 26
"""A packet's stored (compressed) size: a DAVIS346 frame is 90 kB, DV's event packets far less."""
COMPRESSIONS = {0: "none", 1: "LZ4", 2: "LZ4 high", 3: "zstd", 4: "zstd high"}

# AEDAT4 trigger types (dv::TriggerType) kept as edges: the external input's rising (1) and falling (2)
# edges on channel 0, the camera's own signal generator's (4, 5) on channel 1
EDGES = (1, 2, 4, 5)
RISING = (1, 4)
# the APS frame and exposure markers repeat what the frames carry
FRAME_MARKERS = (6, 7, 8, 9)
FRAME_FORMATS = {"L": ("L", 1), "I;16": ("L", 1), "RGB": ("RGB", 3), "RGBA": ("RGB", 3)}


@dataclass(frozen=True)
class Container:
    """What the container walk found: the compression and the number of packets."""

    compression: str
    packets: int


def _header_fields(header: bytes, where: Path) -> tuple[int, int]:
    """(compression, dataTablePosition) of the IOHeader flatbuffer (fields 0 and 1; defaults 0 and
    -1), after checking that its description (field 2) is UTF-8 text: ``aedat`` 2.3 aborts the whole
    process on one that is not, instead of raising."""

    def unpack(fmt: str, at: int) -> int:
        if at < 0 or at + struct.calcsize(fmt) > len(header):
            raise UserError(f"{where}: the AEDAT4 header is damaged (an offset points outside its {len(header)} bytes)")
        return int(struct.unpack_from(fmt, header, at)[0])

    table = unpack("<I", 0)
    vtable = table - unpack("<i", table)
    vtable_size = unpack("<H", vtable)
    offsets = [unpack("<H", vtable + 4 + 2 * field) if 4 + 2 * field + 2 <= vtable_size else 0 for field in range(3)]
    compression = unpack("<i", table + offsets[0]) if offsets[0] else 0
    table_at = unpack("<q", table + offsets[1]) if offsets[1] else -1
    if not offsets[2]:
        raise UserError(f"{where}: the AEDAT4 header has no description of the streams")
    text = table + offsets[2] + unpack("<I", table + offsets[2])
    length = unpack("<I", text)
    if text + 4 + length > len(header):
        raise UserError(f"{where}: the AEDAT4 header is damaged (its description runs past its {len(header)} bytes)")
    try:
        header[text + 4 : text + 4 + length].decode("utf-8")
    except UnicodeDecodeError as exc:
        raise UserError(f"{where}: the AEDAT4 header's description is not UTF-8 text (byte {exc.start})") from None
    return compression, table_at


def walk_container(src: Path) -> Container:
    """Check the container of ``src`` without decoding a packet: the magic line, the header and each
    packet header's size against the file; UserError naming the file for what does not fit."""
    size = src.stat().st_size
    with open(src, "rb") as f:
        magic = f.read(len(MAGIC))
        if magic != MAGIC:
            raise UserError(f"{src}: no '#!AER-DAT4.0' line at the start: not an AEDAT4 file")
        raw = f.read(4)
        if len(raw) < 4:
            raise UserError(f"{src}: truncated: the file ends inside the AEDAT4 header")
        (length,) = struct.unpack("<I", raw)
        if length > MAX_HEADER_BYTES:
            raise UserError(f"{src}: the AEDAT4 header claims {length:,} bytes (at most {MAX_HEADER_BYTES:,} are read)")
        header = f.read(length)
        if len(header) < length:
            raise UserError(f"{src}: truncated: the AEDAT4 header claims {length:,} bytes, the file holds {len(header):,}")
        compression, table_at = _header_fields(header, src)
        if compression not in COMPRESSIONS:
            raise UserError(f"{src}: unknown AEDAT4 compression {compression}")
        data_end = size if table_at < 0 else table_at
        if data_end > size:
            raise UserError(f"{src}: truncated: the header places the file's table at byte {table_at:,}, the file ends at byte {size:,}")
        at, packets = len(MAGIC) + 4 + length, 0
        while at < data_end:
            f.seek(at)
            head = f.read(8)
            if len(head) < 8 or at + 8 > data_end:
                raise UserError(f"{src}: truncated: packet {packets} at byte {at:,} has no complete header (the data end at byte {data_end:,})")
            _, stored = struct.unpack("<iI", head)
            if stored > MAX_PACKET_BYTES:
                raise UserError(f"{src}: packet {packets} at byte {at:,} claims {stored:,} bytes (at most {MAX_PACKET_BYTES:,})")
            if at + 8 + stored > data_end:
                raise UserError(f"{src}: truncated: packet {packets} at byte {at:,} claims {stored:,} bytes, the data end at byte {data_end:,}")
            at += 8 + stored
            packets += 1
    return Container(COMPRESSIONS[compression], packets)


def _decoder_error(src: Path, exc: BaseException) -> UserError:
    return UserError(f"{src}: not a readable AEDAT4 file: {printable(exc)[:300]}")


def packets(src: Path, decoder: Any) -> Iterator[dict[str, Any]]:
    """The decoder's packets; what it raises (RuntimeError, or pyo3's PanicException, a
    BaseException, for what it did not foresee) becomes one UserError naming ``src``."""
    stream = iter(decoder)
    while True:
        try:
            packet = next(stream)
        except StopIteration:
            return
        except (KeyboardInterrupt, SystemExit):
            raise
        except BaseException as exc:
            raise _decoder_error(src, exc) from None
        yield packet


def _times(src: Path, t: Any, what: str) -> np.ndarray:
    """Times as int64 µs (the file's int64 comes through the decoder as uint64: wrapped back here);
    UserError for one beyond the format's ±2⁵³ µs."""
    t = np.asarray(t).astype(np.uint64).view(np.int64)
    beyond = np.flatnonzero(np.abs(t) > MAX_ABS_TIME_US) if t.size else []
    if len(beyond):
        raise UserError(f"{src}: {what} time {int(t.flat[beyond[0]])} µs is beyond ±2^53 µs")
    return t


def check_span(src: Path, first_us: int, last_us: int, limit_bytes: int) -> None:
    """UserError when events from ``first_us`` to ``last_us`` need a millisecond index (int64, one
    entry per ms, spec §6) beyond ``limit_bytes``: one crafted or damaged int64 time would otherwise
    make the writer allocate terabytes."""
    need = ((last_us - first_us) // 1000 + 2) * 8
    if need > limit_bytes:
        raise UserError(
            f"{src}: events from {first_us} µs to {last_us} µs: the capture's millisecond index would take {need:,} bytes, "
            f"beyond {limit_bytes:,} (PSFMT_MAX_ARRAY_BYTES)"
        )


@dataclass
class Streams:
    """The recording's one event stream and, when present, its one frame stream (stream ids)."""

    events: int
    frames: int | None
    width: int
    height: int


def choose_streams(src: Path, id_to_stream: dict[int, dict[str, Any]]) -> Streams:
    """The streams to convert from the decoder's ``id_to_stream``; UserError for a file with none or
    two event streams, two frame streams, or frames of another size than the events."""
    kinds: dict[str, list[int]] = {}
    for sid, info in sorted(id_to_stream.items()):
        kinds.setdefault(str(info.get("type")), []).append(sid)
    for kind in ("events", "frame"):
        if len(kinds.get(kind, [])) > 1:
            raise UserError(f"{src}: {len(kinds[kind])} {kind} streams (a stereo recording?); convert aedat4 reads one camera")
    if not kinds.get("events"):
        raise UserError(f"{src}: no event stream in the AEDAT4 description")
    events = kinds["events"][0]
    width, height = int(id_to_stream[events]["width"]), int(id_to_stream[events]["height"])
    if width < 1 or height < 1:
        raise UserError(f"{src}: the event stream is {width}×{height} pixels")
    frames = kinds["frame"][0] if kinds.get("frame") else None
    if frames is not None:
        size = (int(id_to_stream[frames]["width"]), int(id_to_stream[frames]["height"]))
        if size != (width, height):
            raise UserError(
                f"{src}: the frame stream is {size[0]}×{size[1]}, the event stream {width}×{height}: "
                "convert aedat4 reads cameras whose frames and events share pixels (DAVIS)"
            )
    return Streams(events, frames, width, height)


class FrameSink:
    """Appends frames as they come: checks each against the sensor and the previous frame."""

    def __init__(self, src: Path, writer: psfmt.CaptureWriter, width: int, height: int) -> None:
        self.src, self.writer, self.width, self.height = src, writer, width, height
        self.count = 0
        self.last_start_us: int | None = None
        self.kind: tuple[str, np.dtype[Any]] | None = None

    def __call__(self, frame: dict[str, Any]) -> None:
        k, src = self.count, self.src
        size = (int(frame["width"]), int(frame["height"]), int(frame["offset_x"]), int(frame["offset_y"]))
        if size != (self.width, self.height, 0, 0):
            raise UserError(
                f"{src}: frame {k} is {size[0]}×{size[1]} at ({size[2]}, {size[3]}), not the sensor's "
                f"{self.width}×{self.height}: a DAVIS's frames and events share pixels"
            )
        fmt = str(frame["format"])
        if fmt not in FRAME_FORMATS:
            raise UserError(f"{src}: frame {k} has pixel format {printable(fmt)[:40]!r} (known: {', '.join(FRAME_FORMATS)})")
        order, channels = FRAME_FORMATS[fmt]
        pixels = np.asarray(frame["pixels"])
        if pixels.shape[:2] != (self.height, self.width):
            raise UserError(f"{src}: frame {k} holds {pixels.shape[:2]} pixels for a {self.width}×{self.height} frame")
        pixels = pixels.reshape(self.height, self.width, -1)[..., :channels]
        window = [int(frame[key]) % (1 << 64) for key in ("exposure_begin_t", "exposure_end_t")]
        start, end = (int(v) for v in _times(src, window, f"frame {k}"))
        if end <= start:
            raise UserError(f"{src}: frame {k}'s exposure ends at {end} µs, not after its start at {start} µs")
        if self.last_start_us is not None and start < self.last_start_us:
            raise UserError(f"{src}: frame {k}'s exposure starts at {start} µs, before frame {k - 1}'s at {self.last_start_us} µs")
        kind = (order, pixels.dtype)
        if self.kind is None:
            self.writer.begin_frames(self.height, self.width, channels, pixels.dtype, color_order=order)
            self.kind = kind
        elif kind != self.kind:
            raise UserError(f"{src}: frame {k} is {fmt} {pixels.dtype}, earlier frames {self.kind[0]} {self.kind[1]}")
        self.writer.append_frames(pixels, t_start_us=[start], t_end_us=[end])
        self.last_start_us = start
        self.count += 1


class Aedat4(_EventFile):
    name = "aedat4"
    summary = (
        "iniVation AEDAT4 recordings (DAVIS; extra aedat4): events, frames with their exposure windows, trigger edges, "
        "the identity event→frame affine; light model and calibration"
    )
    options: ClassVar[tuple[Option, ...]] = (*(o for o in ATTACH_OPTIONS if o.name in ("lights", "calibration")), ALLOW_EMPTY)

    def prepare(self, src: Path, options: dict[str, Any]) -> list[str]:
        try:
            import aedat
        except ImportError:
            raise UserError("convert aedat4 needs the aedat package: pip install 'pstoolkit[aedat4]'") from None
        self.container = walk_container(src)
        try:
            self.decoder = aedat.Decoder(str(src))
            id_to_stream = self.decoder.id_to_stream()
        except (KeyboardInterrupt, SystemExit):
            raise
        except BaseException as exc:
            raise _decoder_error(src, exc) from None
        self.streams = choose_streams(src, id_to_stream)
        self.frame_count = 0
        described = ", ".join(f"{sid} {printable(info.get('type'))}" for sid, info in sorted(id_to_stream.items()))
        return [f"aedat4: compression {self.container.compression}, {self.container.packets} packets; streams {described}"]

    def write_events(
        self, src: Path, writer: psfmt.CaptureWriter, options: dict[str, Any], progress: Progress
    ) -> tuple[psfmt.Triggers, str]:
        streams = self.streams
        width, height = streams.width, streams.height
        writer.begin_events(width, height)
        frames = FrameSink(src, writer, width, height)
        monotone = Monotone()
        limit_bytes = psfmt.Limits.from_env().max_array_bytes
        first_us: int | None = None
        triggers: list[psfmt.Triggers] = []
        outside = skipped_triggers = 0
        for k, packet in enumerate(packets(src, self.decoder)):
            sid = packet.get("stream_id")
            if sid == streams.events and "events" in packet:
                block = packet["events"]
                t = _times(src, block["t"], "event")
                x, y = block["x"], block["y"]
                inside = (x < width) & (y < height)
                outside += int(len(block) - np.count_nonzero(inside))
                p = np.where(block["on"], 1, -1).astype(np.int8)
                events = monotone(psfmt.EventArray(x[inside].astype(np.uint16), y[inside].astype(np.uint16), t[inside], p[inside]))
                if len(events):
                    first_us = int(events.t[0]) if first_us is None else first_us
                    check_span(src, first_us, int(events.t[-1]), limit_bytes)
                writer.append_events(events)
            elif sid == streams.frames and "frame" in packet:
                frames(packet["frame"])
            elif "triggers" in packet:
                block = packet["triggers"]
                kind = np.asarray(block["source"], np.uint8)
                keep = np.isin(kind, EDGES)
                skipped_triggers += int(np.count_nonzero(~keep & ~np.isin(kind, FRAME_MARKERS)))
                kept = kind[keep]
                triggers.append(psfmt.Triggers(_times(src, block["t"][keep], "trigger"), kept >= 4, np.isin(kept, RISING)))
            progress(min(1.0, (k + 1) / max(1, self.container.packets)), "packets")
        self.frame_count = frames.count
        notes = []
        if outside:
            notes.append(f"{outside:,} events outside {width}×{height} dropped")
        if skipped_triggers:
            notes.append(f"{skipped_triggers:,} trigger(s) that are no edge (timestamp resets, pulses) skipped")
        return concat_triggers(triggers), _notes(not notes, "; ".join(notes), monotone)

    def complete_calibration(self, calibration: psfmt.Calibration | None) -> psfmt.Calibration | None:
        """The identity event→frame affine where the recording has frames and none was given:
        a DAVIS's frame and event pixels are the same pixels."""
        if self.frame_count == 0:
            return calibration
        calibration = calibration if calibration is not None else psfmt.Calibration()
        if calibration.event_to_frame is None:
            calibration.event_to_frame = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
        return calibration
