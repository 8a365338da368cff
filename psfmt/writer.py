"""Writing hybrid captures: a streaming writer for hardware and converters, and one-call ``write``.

Every write goes to a hidden temporary file in the target's folder and is renamed over the target
only when complete, so an exception, Ctrl-C or a crash never leaves a half file at the target path
and never harms a file already there. Chunks of frames, events and ground-truth maps are shuffled and
deflated in worker threads (``psfmt.deflate``) while the caller goes on, into the standard
streams HDF5's own filters read.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from psfmt import layout
from psfmt.atomic import check_target, commit, temporary_sibling
from psfmt.camera import camera_problem
from psfmt.deflate import ChunkCompressor
from psfmt.errors import FormatError
from psfmt.events import DEFAULT_CHUNK_EVENTS, EVENT_DTYPES, EventArray, MsIndexBuilder
from psfmt.limits import MAX_SENSOR_SIDE, SMALL_CHUNK_BYTES
from psfmt.model import (
    COLOR_ORDERS,
    FRAME_DTYPES,
    Calibration,
    Capture,
    Frames,
    GroundTruth,
    LightSpec,
    Result,
    utc_now,
)
from psfmt.storing import compression_options, put_calibration, put_params, put_result, row_chunks
from psfmt.version import FORMAT_NAME, FORMAT_VERSION_STR

# The event columns grow by at least this many chunks at a time (see ``_flush_events``).
GROW_CHUNKS = 16
SMALL_FRAMES_CHUNK_BYTES = 1 << 16
"""Frames under ``SMALL_CHUNK_BYTES`` share chunks of about this size (a 1×1 frame is no 3-byte chunk)."""


def _package_version() -> str:
    from psfmt import __version__

    return __version__


class CaptureWriter:
    """Writes a capture piece by piece; the file appears at ``path`` only on a successful ``close``.

    Frames and events may be appended in any number of calls as they arrive (events in time order);
    the millisecond index is built incrementally and stored on close. Use as a context manager: leaving
    the block with an exception aborts and removes the temporary file.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        description: str = "",
        creator: str = "psfmt",
        creator_version: str | None = None,
        created: str | None = None,
        compression_level: int = 1,
        event_chunk: int = DEFAULT_CHUNK_EVENTS,
    ) -> None:
        self.path = check_target(path)
        if not self.path.parent.is_dir():
            raise FormatError(self.path, f"folder {self.path.parent} does not exist")
        self._tmp = temporary_sibling(self.path)
        self._compress = compression_options(compression_level)
        # compresses chunks in worker threads while the caller goes on (psfmt.deflate)
        self._chunks = ChunkCompressor()
        self._event_chunk = int(event_chunk)
        try:  # an error or a signal (Ctrl-C, SIGTERM) before the caller holds the writer leaves no file
            self._file = h5py.File(self._tmp, "w")
            attrs = self._file.attrs
            attrs["format"] = FORMAT_NAME
            attrs["format_version"] = FORMAT_VERSION_STR
            attrs["creator"] = creator
            attrs["creator_version"] = creator_version if creator_version is not None else _package_version()
            attrs["created"] = created or utc_now()
            attrs["description"] = description
        except BaseException:
            if hasattr(self, "_file"):
                self._file.close()
            self._tmp.unlink(missing_ok=True)
            raise
        self._frames: h5py.Dataset | None = None
        self._frame_buffer: np.ndarray = np.empty(0)
        self._frame_meta: dict[str, list[np.ndarray]] = {}
        self._events: h5py.Group | None = None
        # the column datasets, looked up once: a group lookup costs about a millisecond in a busy file
        self._event_columns: dict[str, h5py.Dataset] = {}
        self._event_buffer: list[EventArray] = []
        self._buffered = 0
        self._n_events = 0
        self._index = MsIndexBuilder()
        self._closed = False

    # frames ----------------------------------------------------------------------------------------
    def begin_frames(
        self,
        height: int,
        width: int,
        channels: int = 3,
        dtype: Any = np.uint8,
        *,
        color_order: str | None = None,
        bit_depth: int | None = None,
        saturation: float | None = None,
        black_level: float = 0.0,
        response: str = "linear",
    ) -> None:
        """Declare the frame geometry and sensor; ``append_frames`` then adds frames one or more at a time."""
        if self._frames is not None:
            raise FormatError(self.path, "frames were already begun")
        dtype = np.dtype(dtype)
        if dtype not in FRAME_DTYPES:
            raise FormatError(self.path, f"frame dtype {dtype} is not one of uint8, uint16, float32")
        order = color_order or ("RGB" if channels == 3 else "L")
        if COLOR_ORDERS.get(order) != channels:
            raise FormatError(self.path, f"colour order {order!r} does not fit {channels} channels")
        meta = Frames(np.empty((0, height, width, channels), dtype), bit_depth=bit_depth, saturation=saturation)
        # a frame is read without touching the others, but tiny frames share a chunk: one chunk each
        # would cost HDF5 more bookkeeping than data to read (and be refused, MAX_SMALL_CHUNKS)
        frame_bytes = max(1, height * width * channels * dtype.itemsize)
        lead = SMALL_FRAMES_CHUNK_BYTES // frame_bytes if frame_bytes < SMALL_CHUNK_BYTES else 1
        self._frames = self._file.create_dataset(
            f"{layout.FRAMES}/data",
            shape=(0, height, width, channels),
            maxshape=(None, height, width, channels),
            dtype=dtype,
            chunks=row_chunks((height, width, channels), dtype.itemsize, lead=(lead,)),
            **self._compress,
        )
        attrs = self._frames.parent.attrs
        attrs["color_order"] = order
        attrs["bit_depth"] = int(meta.bit_depth)
        attrs["saturation"] = float(meta.saturation)
        attrs["black_level"] = float(black_level)
        attrs["response"] = response

    def append_frames(
        self,
        data: np.ndarray,
        *,
        t_start_us: Any = None,
        t_end_us: Any = None,
        light_direction: Any = None,
        light_intensity: Any = None,
    ) -> None:
        """Append one (H, W, C) frame or a (k, H, W, C) block with its per-frame metadata."""
        data = np.asarray(data)
        if data.ndim == 3:
            data = data[None]
        if self._frames is None:
            self.begin_frames(*data.shape[1:], dtype=data.dtype)
        assert self._frames is not None
        if data.ndim != 4 or data.shape[1:] != self._frames.shape[1:]:
            raise FormatError(self.path, f"frame shape {data.shape[1:]} differs from {self._frames.shape[1:]}")
        if data.dtype != self._frames.dtype:
            raise FormatError(self.path, f"frame dtype {data.dtype} differs from {self._frames.dtype}")
        k = data.shape[0]
        given = {
            "t_start_us": t_start_us,
            "t_end_us": t_end_us,
            "light_direction": light_direction,
            "light_intensity": light_intensity,
        }
        for key, value in given.items():
            if value is None:
                if key in self._frame_meta:
                    raise FormatError(self.path, f"frame {self._frames.shape[0]} lacks {key} that earlier frames have")
                continue
            if key not in self._frame_meta and self._frames.shape[0] > 0:
                raise FormatError(self.path, f"{key} given for frame {self._frames.shape[0]} but not for earlier frames")
            shape = (k,) if key.endswith("_us") else (k, 3)
            arr = np.asarray(value, dtype=np.int64 if key.endswith("_us") else np.float64)
            if arr.size != int(np.prod(shape)):
                raise FormatError(self.path, f"{key} has {arr.size} values for {k} frame(s), expected shape {shape}")
            self._frame_meta.setdefault(key, []).append(arr.reshape(shape))
        n0 = self._frames.shape[0]
        self._frames.resize(n0 + k, axis=0)
        # whole chunks go to the compressor now; the frames of a chunk begun stay until it is full
        pending = np.concatenate([self._frame_buffer, data]) if len(self._frame_buffer) else data
        start = n0 - len(self._frame_buffer)
        lead = self._frames.chunks[0]
        whole = len(pending) // lead * lead
        if whole:
            self._chunks.write(self._frames, pending[:whole], start)
        self._frame_buffer = np.array(pending[whole:])

    # events ----------------------------------------------------------------------------------------
    def begin_events(self, width: int, height: int) -> None:
        """Declare the event sensor geometry (pixels)."""
        if self._events is not None:
            raise FormatError(self.path, "events were already begun")
        for key, side in (("width", width), ("height", height)):
            if not 1 <= int(side) <= MAX_SENSOR_SIDE:
                raise FormatError(self.path, f"event sensor {key} {side} is not within 1…{MAX_SENSOR_SIDE} (x and y are uint16)")
        group = self._file.create_group(layout.EVENTS)
        group.attrs["width"] = int(width)
        group.attrs["height"] = int(height)
        for c, dtype in EVENT_DTYPES.items():
            self._event_columns[c] = group.create_dataset(
                c, shape=(0,), maxshape=(None,), dtype=dtype, chunks=(self._event_chunk,), **self._compress
            )
        self._events = group

    def append_events(self, events: EventArray) -> None:
        """Append events that are sorted and not earlier than those already written."""
        if self._events is None:
            raise FormatError(self.path, "begin_events(width, height) must come before append_events")
        if len(events) == 0:
            return
        t = events.t
        if not events.is_sorted():
            raise FormatError(self.path, "appended events are not sorted by time")
        last = self._index.t_last_us
        if last is not None and t[0] < last:
            raise FormatError(self.path, f"appended events start at {t[0]} µs, before the last written {last} µs")
        self._index.add(t)
        self._event_buffer.append(events)
        self._buffered += len(events)
        if self._buffered >= self._event_chunk:
            self._flush_events(final=False)

    @property
    def event_count(self) -> int:
        """Events appended so far."""
        return self._n_events + self._buffered

    def _flush_events(self, final: bool) -> None:
        assert self._events is not None
        block = EventArray.concatenate(self._event_buffer)
        # whole storage chunks only, so compressed chunks are written once and never rewritten
        cut = len(block) if final else (len(block) // self._event_chunk) * self._event_chunk
        n0 = self._n_events
        room = self._event_columns["t"].shape[0]
        for c in "xytp":
            ds = self._event_columns[c]
            # a resize costs about 0.2 ms in a file busy with chunk writes: the columns grow ahead
            # (whole chunks only are written before the end) and take their exact length last, before
            # the partial last chunk exists, so no written chunk is cut
            if final:
                ds.resize(n0 + cut, axis=0)
            elif n0 + cut > room:
                ds.resize(max(n0 + cut, 2 * room, GROW_CHUNKS * self._event_chunk), axis=0)
            # the block is the writer's own (a concatenation), left as it is: no copies of its chunks
            self._chunks.write(ds, getattr(block, c)[:cut], n0, copy=False)
        self._n_events += cut
        rest = block[cut:]
        self._event_buffer = [rest] if len(rest) else []
        self._buffered = len(rest)

    def _finish_events(self) -> None:
        assert self._events is not None
        self._flush_events(final=True)
        index = self._index.finish()
        self._events.create_dataset("ms_to_idx", data=index, chunks=(min(len(index), 1 << 14),))
        self._events.attrs["ms_origin_us"] = self._index.origin_us

    # everything else -------------------------------------------------------------------------------
    def set_triggers(self, t: Any, channel: Any, value: Any) -> None:
        group = self._file.create_group(layout.TRIGGERS)
        group.create_dataset("t", data=np.asarray(t, np.int64))
        group.create_dataset("channel", data=np.asarray(channel, np.uint8))
        group.create_dataset("value", data=np.asarray(value, np.int8))

    def set_lights(self, lights: LightSpec) -> None:
        group = self._file.create_group(layout.LIGHTS)
        group.attrs["model"] = lights.model
        put_params(group, lights.params)

    def set_calibration(self, calibration: Calibration) -> None:
        """``/calibration``; a camera model and intrinsics that do not go together (spec §9.1) are refused."""
        problem = camera_problem(calibration.camera_model, calibration.intrinsics)
        if problem is not None:
            raise FormatError(self.path, f"calibration: {problem}")
        put_calibration(self._file, calibration)

    def set_ground_truth(self, gt: GroundTruth) -> None:
        group = self._file.create_group(layout.GROUND_TRUTH)
        for key in layout.GT_MAPS:
            value = getattr(gt, key)
            if value is not None:
                self._put_map(group, key, np.asarray(value, np.uint8 if key == "mask" else np.float32))
        if gt.materials:
            mats = group.create_group(layout.MATERIALS)
            for key, value in gt.materials.items():
                self._put_map(mats, key, np.asarray(value, np.float32))

    def _put_map(self, group: h5py.Group, key: str, value: np.ndarray) -> None:
        if not (self._compress and value.ndim and value.size):
            group.create_dataset(key, data=value)
            return
        ds = group.create_dataset(key, shape=value.shape, dtype=value.dtype,
                                  chunks=row_chunks(value.shape, value.dtype.itemsize), **self._compress)
        self._chunks.write(ds, value)

    def add_result(self, result: Result) -> None:
        put_result(self._file, result, self._compress)

    # finishing -------------------------------------------------------------------------------------
    def close(self) -> Path:
        """Finalise the index and metadata, then move the file into place. Returns the final path."""
        if self._closed:
            return self.path
        try:
            if self._frames is not None:
                if len(self._frame_buffer):  # the last chunk, in part
                    self._chunks.write(self._frames, self._frame_buffer, self._frames.shape[0] - len(self._frame_buffer))
                for key, parts in self._frame_meta.items():
                    self._frames.parent.create_dataset(key, data=np.concatenate(parts))
            if self._events is not None:
                self._finish_events()
            if layout.CALIBRATION not in self._file:
                self.set_calibration(Calibration())
            self._chunks.flush()
            self._chunks.close()
            self._file.close()
            commit(self._tmp, self.path)
        except BaseException:
            self.abort()
            raise
        self._closed = True
        return self.path

    def abort(self) -> None:
        """Drop everything written so far; the target path is untouched."""
        self._closed = True
        try:
            self._chunks.close()
            self._file.close()
        finally:
            self._tmp.unlink(missing_ok=True)

    def __enter__(self) -> CaptureWriter:
        return self

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def write(capture: Capture, path: str | os.PathLike[str], *, compression_level: int = 1) -> Path:
    """Write ``capture`` to ``path`` atomically. Lazy frames and events are copied in bounded memory."""
    with CaptureWriter(
        path,
        description=capture.description,
        creator=capture.creator,
        creator_version=capture.creator_version or None,
        created=capture.created,
        compression_level=compression_level,
    ) as writer:
        frames = capture.frames
        if frames is not None:
            writer.begin_frames(
                frames.height,
                frames.width,
                frames.channels,
                frames.data.dtype,
                color_order=frames.color_order,
                bit_depth=frames.bit_depth,
                saturation=frames.saturation,
                black_level=frames.black_level,
                response=frames.response,
            )
            for k in range(frames.count):
                writer.append_frames(
                    frames.frame(k),
                    **{
                        key: getattr(frames, key)[k : k + 1]
                        for key in layout.FRAME_WINDOW + layout.FRAME_INSTANT
                        if getattr(frames, key) is not None
                    },
                )
        if capture.events is not None:
            writer.begin_events(capture.events.width, capture.events.height)
            for block in capture.events.chunks():
                writer.append_events(block)
        if capture.triggers is not None:
            writer.set_triggers(capture.triggers.t, capture.triggers.channel, capture.triggers.value)
        if capture.lights is not None:
            writer.set_lights(capture.lights)
        writer.set_calibration(capture.calibration)
        if capture.ground_truth is not None:
            writer.set_ground_truth(capture.ground_truth)
        for result in capture.results.values():
            writer.add_result(result)
    return Path(path)
