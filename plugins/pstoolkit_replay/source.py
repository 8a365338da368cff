"""The ``replay`` camera source: plays a recorded capture as if it were the rig's cameras.

Frames (each once its exposure window has ended), events in slices of ``slice_us`` and trigger edges
come out in time order on the recording's clock, at real speed (``speed=1``), faster (``speed=10``)
or as fast as the consumer takes them (``speed=0``). A recording without stored triggers gets the
edges the ring light's period trigger would have produced: a 10 µs pulse at the start of each turn
of its light model (where the trajectory is at its phase, LED 0 of the ring light).
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

import psfmt
from pstoolkit import Option, UserError
from pstoolkit.hardware.backend import (
    CameraSource,
    EventBlock,
    EventSensor,
    FrameBlock,
    FrameSensor,
    Packet,
    Sweep,
    TriggerBlock,
)

PULSE_US = 10


def _period_start_us(lights: psfmt.LightSpec) -> float:
    """When a periodic light model begins a turn: ``t0_us`` of ring models, the first sample of a
    sampled one."""
    if "t0_us" in lights.params:
        return float(lights.params["t0_us"])
    if "times_us" in lights.params:
        return float(np.asarray(lights.params["times_us"]).reshape(-1)[0])
    return 0.0


class Replay(CameraSource):
    name = "replay"
    summary = "plays a capture file as if it were the rig: frames, events and triggers in time order"
    options = (
        Option("speed", float, 1.0, "playback speed: 1 real time, 10 ten times faster, 0 as fast as possible", minimum=0.0),
        Option("slice_us", int, 1000, "length of the event blocks played at once, µs", minimum=1),
    )

    def open(self) -> None:
        path = Path(self.location)
        if not path.exists():
            raise UserError(f"replay {path}: does not exist")
        self.capture = psfmt.read(path)
        capture = self.capture
        frames = capture.frames
        if frames is not None:
            if not frames.has_windows:
                capture.close()
                raise UserError(f"replay {path}: its frames have no exposure windows (a classic capture cannot be replayed in time)")
            self.frame_sensor = FrameSensor(
                frames.height, frames.width, frames.channels, frames.data.dtype,
                bit_depth=frames.bit_depth, saturation=frames.saturation, black_level=frames.black_level,
                color_order=frames.color_order,
            )
        if capture.events is not None:
            cal = capture.calibration
            self.event_sensor = EventSensor(
                capture.events.width, capture.events.height, cal.contrast_pos, cal.contrast_neg, cal.refractory_us
            )
        if frames is None and capture.events is None:
            capture.close()
            raise UserError(f"replay {path}: holds neither frames nor events")
        self.calibration = capture.calibration
        period = capture.lights.params.get("period_us") if capture.lights is not None else None
        self.period_us = round(float(period)) if period is not None else None

    def close(self) -> None:
        self.capture.close()

    def _span_us(self) -> tuple[int, int]:
        starts, ends = [], []
        frames = self.capture.frames
        if frames is not None and frames.count:
            starts.append(int(frames.t_start_us[0]))
            ends.append(int(frames.t_end_us.max()))
        events = self.capture.events
        if events is not None and len(events):
            starts.append(int(events.t_first_us))
            ends.append(int(events.t_last_us) + 1)
        if not starts:
            raise UserError(f"replay {self.location}: the recording is empty")
        return min(starts), max(ends)

    def _triggers(self, t_first: int, t_last: int) -> psfmt.Triggers:
        if self.capture.triggers is not None:
            return self.capture.triggers
        lights = self.capture.lights
        if lights is None or self.period_us is None:
            raise UserError(f"replay {self.location}: has neither triggers nor a periodic light model to derive them from")
        start = _period_start_us(lights)
        k = np.arange(np.ceil((t_first - start) / self.period_us), np.floor((t_last - start) / self.period_us) + 1)
        rising = np.round(start + k * self.period_us).astype(np.int64)
        t = np.stack([rising, rising + PULSE_US], axis=-1).reshape(-1)
        return psfmt.Triggers(t, np.zeros(len(t)), np.tile([1, 0], len(rising)))

    def stream(self, sweep: Sweep) -> Iterator[Packet]:
        if self.period_us is not None and sweep.period_us != self.period_us:
            raise UserError(
                f"replay {self.location}: recorded with a {self.period_us} µs light period, but the light is set to {sweep.period_us} µs"
            )
        t_first, t_last = self._span_us()
        triggers = self._triggers(t_first, t_last)
        frames = self.capture.frames
        events = self.capture.events
        step = int(self.settings["slice_us"])
        speed = float(self.settings["speed"])
        wall0 = time.monotonic()
        for t in range(t_first, t_last + step, step):
            packets: list[Packet] = []
            hit = (triggers.t >= t) & (triggers.t < t + step)
            if hit.any():
                packets.append(TriggerBlock(triggers.t[hit], triggers.channel[hit], triggers.value[hit]))
            if frames is not None:
                done = np.flatnonzero((frames.t_end_us >= t) & (frames.t_end_us < t + step))
                packets += [
                    FrameBlock(frames.frame(int(k))[None], frames.t_start_us[k : k + 1], frames.t_end_us[k : k + 1]) for k in done
                ]
            if events is not None:
                block = events.window(t, t + step)
                if len(block):
                    packets.append(EventBlock(block, t + step))
            for packet in sorted(packets, key=lambda p: p.t_us):
                if speed > 0:
                    time.sleep(max(0.0, wall0 + (packet.t_us - t_first) / 1e6 / speed - time.monotonic()))
                yield packet
