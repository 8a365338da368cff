"""The ``ringlight`` light backend: a serial ring-light controller driven through ``RingLightClient``."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

import psfmt
from pstoolkit import Option, SampledLight, UserError
from pstoolkit.hardware.backend import LightBackend, Sweep
from pstoolkit_ringlight.client import DeviceError, RingLightClient
from pstoolkit_ringlight.protocol import TRIGGERS


def read_gains(path: Path, leds: int) -> np.ndarray:
    """Per-LED calibration gains (leds, 3) in 0…255 from a text file of ``r g b`` lines, one per LED."""
    try:
        gains = np.loadtxt(path, ndmin=2)
    except (OSError, ValueError) as exc:
        raise UserError(f"{path}: cannot read LED gains ({str(exc).strip().splitlines()[0]})") from None
    if gains.shape != (leds, 3):
        raise UserError(f"{path}: expected {leds} lines of 'r g b' gains for {leds} LEDs, got shape {gains.shape}")
    if np.any(gains < 0) or np.any(gains > 255) or np.any(gains != np.round(gains)):
        raise UserError(f"{path}: gains must be whole numbers from 0 to 255")
    return gains.astype(int)


def ring_light_spec(leds: int, sweep: Sweep, t0_us: int, elevation_deg: float, phase_deg: float) -> psfmt.LightSpec:
    """The trajectory of a sweep over a ring of ``leds`` directional LEDs at ``elevation_deg``
    (numbered counter-clockwise, LED 0 at ``phase_deg``): step k lights LED sense·k mod leds, at
    azimuth phase_deg + sense·360°·k/leds, at its peak at t0 + k·period/leds. Smooth: the light blends
    from each LED to the next (the ``sampled`` model's interpolation); otherwise each LED holds its
    slot, written as two samples (slot start, 1 µs before the next slot). Gains equalise the LEDs,
    so every intensity is 1."""
    i = np.arange(leds, dtype=np.float64)
    azimuth = np.deg2rad(phase_deg + sweep.sense * 360.0 * i / leds)
    e = np.deg2rad(elevation_deg)
    directions = np.stack([np.cos(e) * np.cos(azimuth), np.cos(e) * np.sin(azimuth), np.full(leds, np.sin(e))], axis=-1)
    slot_us = sweep.period_us / leds
    times = t0_us + i * slot_us
    if not sweep.smooth:
        times = np.stack([times, times + slot_us - 1.0], axis=-1).reshape(-1)
        directions = np.repeat(directions, 2, axis=0)
    model = SampledLight(
        times_us=np.round(times), directions=directions, intensities=np.ones((len(times), 3)), periodic=True, period_us=float(sweep.period_us)
    )
    return model.to_spec()


class RingLightBackend(LightBackend):
    name = "ringlight"
    summary = "serial ring-light controller (spec/ringlight-protocol.md); --port sim for the simulated one"
    options = (
        Option("elevation_deg", float, 45.0, "elevation of the LEDs seen from the object, degrees", minimum=0.0, maximum=90.0),
        Option("phase_deg", float, 0.0, "azimuth of LED 0 in the camera frame (x right, y up), degrees"),
        Option("gains", str, "", "text file of per-LED 'r g b' calibration gains 0-255, one line per LED (empty: all 255)"),
        Option("timeout_ms", int, 200, "reply deadline of one try, ms", minimum=1),
        Option("retries", int, 3, "tries after the first before giving up", minimum=0, maximum=20),
        Option("watchdog_ms", int, 1000, "the device turns the lights off after this much silence, ms", minimum=100, maximum=60000),
        Option("baudrate", int, 115200, "serial baud rate", minimum=300),
    )

    def __init__(self, port: str, options: dict[str, Any]) -> None:
        super().__init__(port, options)
        self.client = RingLightClient(
            port, timeout_s=options["timeout_ms"] / 1000.0, retries=options["retries"], baudrate=options["baudrate"]
        )

    @property
    def leds(self) -> int:
        if self.client.info is None:
            raise UserError(f"ring light on {self.port}: not connected")
        return self.client.info.leds

    @property
    def keepalive_s(self) -> float:
        return self.settings["watchdog_ms"] / 4000.0

    def open(self) -> None:
        self.client.connect()
        self.client.request("OFF")
        self.client.request("WDG", self.settings["watchdog_ms"])
        if self.settings["gains"]:
            for led, (r, g, b) in enumerate(read_gains(Path(self.settings["gains"]), self.leds)):
                self.client.request("CAL", led, r, g, b)

    def configure(self, sweep: Sweep) -> None:
        if sweep.trigger not in TRIGGERS:
            raise UserError(f"ring light: trigger {sweep.trigger!r} is not one of {', '.join(TRIGGERS)}")
        if sweep.period_us < 2 * self.leds:
            raise UserError(f"ring light on {self.port}: a period of {sweep.period_us} µs is too short for {self.leds} LEDs")
        self.client.request("CFG", sweep.period_us, sweep.sense, int(sweep.smooth), TRIGGERS[sweep.trigger], sweep.exposures)

    def start(self) -> None:
        self.client.request("GO", 0)

    def stop(self) -> None:
        self.client.request("STOP")

    def keepalive(self) -> None:
        reopened = self.client.reopened
        self.client.request("PING")
        # many boards reset when their port is reopened: a sweep that did not survive spoils the capture
        if self.client.reopened != reopened and self.status()["state"] != "SWEEP":
            raise DeviceError(f"ring light on {self.port}: the connection was lost and the sweep did not survive it")

    def status(self) -> dict[str, Any]:
        state, turns, watchdog_ms, fault = self.client.request("STAT")
        return {"state": state, "turns": int(turns), "watchdog_ms": int(watchdog_ms), "fault": fault}

    def off(self) -> None:
        try:
            self.client.request("OFF")
        except Exception:  # off() runs on the way out of errors; the device watchdog covers a dead link
            pass

    def close(self) -> None:
        self.client.close()

    def light_spec(self, sweep: Sweep, t0_us: int) -> psfmt.LightSpec:
        return ring_light_spec(self.leds, sweep, t0_us, self.settings["elevation_deg"], self.settings["phase_deg"])
