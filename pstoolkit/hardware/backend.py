"""The hardware-backend interface: light rigs and camera sources that ``pstoolkit capture`` drives.

Two kinds of backend share the ``backends`` registry (``pstoolkit_register_backends``):

- a ``LightBackend`` drives the light rig (a serial ring light …): connect and check the device,
  configure a sweep, start and stop it, and always leave the lights off (``off`` never raises);
  it knows the light trajectory it produces and returns it as a ``psfmt.LightSpec``.
- a ``CameraSource`` delivers what a camera records (frames with their exposure windows, events,
  trigger edges), as ``Packet`` blocks in time order on the capture clock. A vendor SDK (Prophesee
  Metavision, an industrial frame camera) plugs in as a third-party ``CameraSource``.

``record`` streams the packets of one or more sources into a ``psfmt.CaptureWriter`` and keeps the
light alive meanwhile; the caller owns the writer, so an exception leaves no file (see
``docs/hardware.md``).
"""

from __future__ import annotations

import heapq
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

import psfmt
from pstoolkit.errors import UserError
from pstoolkit.plugin.options import Option
from pstoolkit.plugin.registry import Entry, PluginError

TRIGGER_MODES = ("off", "period", "exposure")


@dataclass(frozen=True)
class Sweep:
    """A light sweep: one turn every ``period_us``, ``sense`` +1 (counter-clockwise seen from the
    camera, the ``ring`` model's sense) or -1; ``smooth`` blends neighbouring LEDs so the light moves
    continuously; the trigger output (one of ``TRIGGER_MODES``) fires never, once per period or once
    per exposure window (``exposures`` windows per period)."""

    period_us: int
    sense: int = 1
    smooth: bool = True
    trigger: str = "period"
    exposures: int = 1


@dataclass(frozen=True)
class FrameSensor:
    """Geometry and encoding of a frame camera's images (see ``psfmt.Frames``)."""

    height: int
    width: int
    channels: int = 3
    dtype: Any = np.uint8
    bit_depth: int | None = None
    saturation: float | None = None
    black_level: float = 0.0
    color_order: str | None = None


@dataclass(frozen=True)
class EventSensor:
    """Geometry of an event camera, with what is known of its thresholds (natural-log units) and
    refractory period (µs)."""

    width: int
    height: int
    contrast_pos: float | None = None
    contrast_neg: float | None = None
    refractory_us: float | None = None


@dataclass
class FrameBlock:
    """Frames (k, H, W, C) with their exposure windows [t_start_us, t_end_us)."""

    data: np.ndarray
    t_start_us: np.ndarray
    t_end_us: np.ndarray

    @property
    def t_us(self) -> int:
        """When the block is complete: the end of its last exposure."""
        return int(self.t_end_us[-1])


@dataclass
class EventBlock:
    """Events in time order; ``t_end_us`` is the end of the time slice they cover (exclusive)."""

    events: psfmt.EventArray
    t_end_us: int

    @property
    def t_us(self) -> int:
        return self.t_end_us


@dataclass
class TriggerBlock:
    """Trigger edges seen by a camera's trigger input: time µs, input channel, edge (1 rising, 0 falling)."""

    t: np.ndarray
    channel: np.ndarray
    value: np.ndarray

    @property
    def t_us(self) -> int:
        return int(self.t[-1])


Packet = FrameBlock | EventBlock | TriggerBlock


class LightBackend(ABC):
    """Base of light rigs: ``name``, ``summary``, typed ``options``. Use as a context manager: leaving
    the block, normally or by an exception or Ctrl-C, turns the lights off and disconnects."""

    name: ClassVar[str]
    summary: ClassVar[str]
    options: ClassVar[tuple[Option, ...]] = ()
    role: ClassVar[str] = "light"

    def __init__(self, port: str, options: dict[str, Any]) -> None:
        self.port = port
        self.settings = options

    @abstractmethod
    def open(self) -> None:
        """Connect and check the device (identity, version); UserError naming the port on failure."""

    @abstractmethod
    def configure(self, sweep: Sweep) -> None:
        """Load a sweep; the lights stay off until ``start``."""

    @abstractmethod
    def start(self) -> None:
        """Start the configured sweep."""

    @abstractmethod
    def stop(self) -> None:
        """Stop the sweep and turn the lights off."""

    @abstractmethod
    def keepalive(self) -> None:
        """Tell the device the host is still there (feeds its watchdog); call at least every
        ``keepalive_s`` seconds while the lights are on."""

    @abstractmethod
    def off(self) -> None:
        """All lights off, best effort: never raises, whatever state the connection is in."""

    @abstractmethod
    def close(self) -> None:
        """Disconnect (after ``off``)."""

    @abstractmethod
    def light_spec(self, sweep: Sweep, t0_us: int) -> psfmt.LightSpec:
        """The light trajectory of ``sweep`` started (LED 0 at its peak) at ``t0_us`` on the capture clock."""

    @property
    def keepalive_s(self) -> float:
        return 0.5

    def __enter__(self) -> LightBackend:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        try:
            self.off()
        finally:
            self.close()


class CameraSource(ABC):
    """Base of camera sources: ``name``, ``summary``, typed ``options``; created with a ``location``
    (a file, a device serial number …). ``open`` reads what the source knows before recording."""

    name: ClassVar[str]
    summary: ClassVar[str]
    options: ClassVar[tuple[Option, ...]] = ()
    role: ClassVar[str] = "source"

    def __init__(self, location: str, options: dict[str, Any]) -> None:
        self.location = location
        self.settings = options
        self.frame_sensor: FrameSensor | None = None
        self.event_sensor: EventSensor | None = None
        self.calibration: psfmt.Calibration | None = None
        self.period_us: int | None = None

    @abstractmethod
    def open(self) -> None:
        """Connect (or open the file); fill ``frame_sensor``/``event_sensor`` and, where the source
        dictates them, ``period_us`` and ``calibration``. UserError on failure."""

    @abstractmethod
    def stream(self, sweep: Sweep) -> Iterator[Packet]:
        """Start recording and yield packets in time order (by ``t_us``) until the source ends or
        the generator is closed, which stops the camera."""

    def close(self) -> None:  # noqa: B027 -- optional: a source with nothing to release keeps the no-op
        """Release the camera or file."""

    def __enter__(self) -> CameraSource:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def backend_class(entry: Entry, role: str) -> type:
    """The class of a registry entry that must be a light (``role="light"``) or a camera source."""
    base = LightBackend if role == "light" else CameraSource
    if not (isinstance(entry.obj, type) and issubclass(entry.obj, (LightBackend, CameraSource))):
        raise PluginError(f"plugin {entry.plugin!r}: backend {entry.name!r} is not a pstoolkit.hardware.backend.LightBackend or CameraSource")
    if not issubclass(entry.obj, base):
        raise UserError(f"backend {entry.name!r} is a {entry.obj.role}, not a {role}")
    return entry.obj


@dataclass
class Recording:
    """What ``record`` wrote: frames and events counted, the trigger edges inside the turns, and the
    recorded span [t0_us, t_end_us) on the capture clock."""

    frames: int = 0
    events: int = 0
    t0_us: int = 0
    t_end_us: int = 0
    triggers: list[TriggerBlock] = field(default_factory=list)


def _first_rising(block: TriggerBlock, channel: int) -> int | None:
    hits = np.flatnonzero((block.channel == channel) & (block.value == 1))
    return int(block.t[hits[0]]) if hits.size else None


def record(
    sources: Sequence[CameraSource],
    writer: psfmt.CaptureWriter,
    sweep: Sweep,
    periods: int,
    keepalive: Callable[[], None],
    keepalive_s: float,
    *,
    trigger_channel: int = 0,
    progress: Callable[[float, str], None] | None = None,
) -> Recording:
    """Stream the sources into ``writer`` for a whole number of turns of the sweep, counted from the
    first rising trigger edge. Frames whose exposure window lies inside the turns, and events and
    trigger edges inside them, are kept; the sources are closed on return.

    Parameters
    ----------
    sources
        The open camera sources; their packets are merged in time order.
    writer
        The capture being written, its frames and events begun by the caller.
    sweep
        The light sweep the sources record; its ``period_us`` sets the length of a turn.
    periods
        Turns to record.
    keepalive, keepalive_s
        ``keepalive()`` runs every ``keepalive_s`` wall seconds while recording (e.g. to keep the light
        running).
    trigger_channel
        Channel of the light's period trigger (LED 0 at its peak); its first rising edge starts the turns.
    progress
        Optional ``progress(fraction, stage)`` called after each packet written.

    Returns
    -------
    Recording
        Frames and events counted, the trigger edges inside the turns, and the span [t0_us, t_end_us) on
        the capture clock.

    Raises
    ------
    UserError
        The sources ended before a rising trigger edge or before the last turn was complete (the
        caller's writer then aborts, so no partial file appears).
    """
    streams = [source.stream(sweep) for source in sources]
    out = Recording()
    t0: int | None = None
    last_seen: int | None = None
    last_alive = time.monotonic()
    waiting: list[Packet] = []  # packets before the sweep start is known
    finished = False
    try:
        for packet in heapq.merge(*streams, key=lambda item: item.t_us):
            if finished and packet.t_us > out.t_end_us:
                break
            if time.monotonic() - last_alive >= keepalive_s:
                keepalive()
                last_alive = time.monotonic()
            last_seen = packet.t_us
            if t0 is None:
                if isinstance(packet, TriggerBlock):
                    t0 = _first_rising(packet, trigger_channel)
                waiting.append(packet)
                if t0 is None:
                    continue
                out.t0_us, out.t_end_us = t0, t0 + periods * sweep.period_us
            for item in waiting or [packet]:
                _write(item, writer, out)
            waiting = []
            if progress is not None:
                progress((packet.t_us - out.t0_us) / (out.t_end_us - out.t0_us), "recording")
            # packets of other sources that end at the same time still belong to the turns
            finished = packet.t_us >= out.t_end_us
    finally:
        for stream in streams:
            stream.close()
    if finished:
        return out
    if t0 is None:
        raise UserError(f"the sources ended before a rising trigger edge on channel {trigger_channel}: the sweep start was never seen")
    done = (max(t0, last_seen or t0) - t0) / sweep.period_us
    raise UserError(f"the sources ended after {done:.2f} of {periods} period(s)")


def _write(packet: Packet, writer: psfmt.CaptureWriter, out: Recording) -> None:
    t0, t_end = out.t0_us, out.t_end_us
    if isinstance(packet, FrameBlock):
        keep = (packet.t_start_us >= t0) & (packet.t_end_us <= t_end)
        if keep.any():
            writer.append_frames(packet.data[keep], t_start_us=packet.t_start_us[keep], t_end_us=packet.t_end_us[keep])
            out.frames += int(keep.sum())
    elif isinstance(packet, EventBlock):
        events = packet.events.window(t0, t_end)
        writer.append_events(events)
        out.events += len(events)
    else:
        keep = (packet.t >= t0) & (packet.t < t_end)
        if keep.any():
            out.triggers.append(TriggerBlock(packet.t[keep], packet.channel[keep], packet.value[keep]))
