"""A simulated ring-light controller: the firmware of ``examples/firmware/ringlight`` in Python.

It answers protocol frames exactly as the sketch does (same commands, errors, duplicate-id rule,
watchdog, sweep) on a clock it is given, so tests and demos drive it through real pyserial I/O
(the ``ringlightsim://`` URL handler or a pty pair). Faults can be injected to test the host side:
replies dropped or corrupted, garbage answers, a disconnect after some requests.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

from pstoolkit_ringlight.protocol import (
    E_CRC,
    E_LONG,
    E_RANGE,
    E_STATE,
    E_SYNTAX,
    E_UNKNOWN,
    FIRMWARE_NAME,
    MAX_LINE,
    NO_ID,
    PROTOCOL_VERSION,
    REPLY,
    REQUEST,
    ProtocolError,
    decode,
    encode,
)

FIRMWARE_VERSION = "1.0.0"
WATCHDOG_MS = (100, 60000)
PERIOD_US = (1000, 10_000_000)


@dataclass
class Faults:
    """Injected faults, by the 1-based number of the request received: ``drop`` (no reply),
    ``corrupt`` (reply with a wrong checksum), ``blip`` (the connection breaks once, after the device
    acted, and can be reopened), ``garbage`` (every answer is noise), ``disconnect`` (the port dies
    for good after this many requests); ``reset``: opening the port restarts the controller, as the
    DTR line does on most Arduino boards."""

    drop: set[int] = field(default_factory=set)
    corrupt: set[int] = field(default_factory=set)
    blip: set[int] = field(default_factory=set)
    garbage: bool = False
    disconnect: int = 0
    reset: bool = False


class SimulatedRingLight:
    """The controller's state machine. ``receive(line)`` returns the bytes it answers; time comes from ``clock``."""

    def __init__(
        self,
        leds: int = 60,
        firmware: str = FIRMWARE_NAME,
        version: str = FIRMWARE_VERSION,
        protocol: int = PROTOCOL_VERSION,
        faults: Faults | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.leds = leds
        self.identity = (firmware, version, str(leds), str(protocol))
        self.faults = faults or Faults()
        self.clock = clock
        self.requests = 0
        self.restart()

    def restart(self) -> None:
        """Power-up state: lights off, no sweep configured, default gains and watchdog."""
        self.watchdog_ms = 1000
        self.gains = [(255, 255, 255)] * self.leds
        self.config: tuple[int, int, int, int, int] | None = None
        self.state = "IDLE"
        self.fault = "NONE"
        self.single: tuple[int, int, int, int] | None = None
        self.turns = 0
        self.started_s = 0.0
        self.last_rx_s = self.clock()
        self.last_id: str | None = None
        self.last_reply = b""

    # what an observer of the LEDs would see ----------------------------------------------------
    def _advance(self, now_s: float) -> None:
        """Apply the watchdog and the end of a finite sweep up to ``now_s``."""
        if self.state == "IDLE":
            return
        if now_s - self.last_rx_s > self.watchdog_ms / 1000.0:
            self.state, self.fault, self.single = "IDLE", "WDOG", None
        elif self.state == "SWEEP" and self.turns and self.config is not None and (now_s - self.started_s) * 1e6 >= self.turns * self.config[0]:
            self.state = "IDLE"

    def lit(self, now_s: float | None = None) -> bool:
        """Whether any LED is on at ``now_s`` (default: now)."""
        self._advance(self.clock() if now_s is None else now_s)
        return self.state != "IDLE"

    def turns_done(self, now_s: float) -> int:
        if self.config is None or self.state != "SWEEP":
            return 0
        return int((now_s - self.started_s) * 1e6 // self.config[0])

    # the protocol ------------------------------------------------------------------------------
    @property
    def disconnected(self) -> bool:
        return 0 < self.faults.disconnect <= self.requests

    def receive(self, line: bytes) -> bytes:
        """Handle one line from the host (without its newline) and return the reply bytes."""
        now = self.clock()
        self._advance(now)
        self.requests += 1
        n = self.requests
        if self.faults.garbage:
            return b"\x00\xfe?? ringlight ready >>\r\n"
        reply = self._handle(line, now)
        if n in self.faults.drop:
            return b""
        if n in self.faults.corrupt:
            return reply[:-3] + (b"00" if not reply.endswith(b"00\n") else b"01") + b"\n"
        return reply

    def _error(self, request_id: str, code: int) -> bytes:
        return encode(REPLY, [request_id, "ER", str(code)])

    def _handle(self, line: bytes, now: float) -> bytes:
        if len(line) > MAX_LINE:
            return self._error(NO_ID, E_LONG)
        try:
            words = decode(line, REQUEST)
        except ProtocolError as exc:
            return self._error(NO_ID, E_CRC if "checksum" in str(exc) else E_SYNTAX)
        request_id = words[0]
        if len(request_id) != 2 or len(words) < 2:
            return self._error(NO_ID, E_SYNTAX)
        self.last_rx_s = now
        if request_id == self.last_id:
            return self.last_reply  # a retry after a lost reply: answer again, do not act twice
        try:
            args = [int(w) for w in words[2:]]
        except ValueError:
            reply = self._error(request_id, E_SYNTAX)
        else:
            code, fields = self._command(words[1], args, now)
            reply = encode(REPLY, [request_id, "OK", *fields]) if code == 0 else self._error(request_id, code)
        self.last_id, self.last_reply = request_id, reply
        return reply

    def _command(self, op: str, args: list[int], now: float) -> tuple[int, list[str]]:
        arity = {"ID": 0, "PING": 0, "STAT": 0, "OFF": 0, "STOP": 0, "WDG": 1, "GO": 1, "CFG": 5, "CAL": 4, "LED": 4}
        if op not in arity:
            return E_UNKNOWN, []
        if len(args) != arity[op]:
            return E_SYNTAX, []
        if op == "ID":
            return 0, list(self.identity)
        if op == "PING":
            return 0, []
        if op == "STAT":
            state = self.state
            return 0, [state, str(self.turns_done(now)), str(self.watchdog_ms), self.fault]
        if op in ("OFF", "STOP"):
            self.state, self.single = "IDLE", None
            return 0, []
        if op == "WDG":
            if not WATCHDOG_MS[0] <= args[0] <= WATCHDOG_MS[1]:
                return E_RANGE, []
            self.watchdog_ms = args[0]
            return 0, []
        if op == "CFG":
            period, sense, smooth, trigger, exposures = args
            if self.state == "SWEEP":
                return E_STATE, []
            ok = (
                PERIOD_US[0] <= period <= PERIOD_US[1]
                and period >= 2 * self.leds
                and sense in (-1, 1)
                and smooth in (0, 1)
                and trigger in (0, 1, 2)
                and 1 <= exposures <= 100
            )
            if not ok:
                return E_RANGE, []
            self.config = (period, sense, smooth, trigger, exposures)
            return 0, []
        if op == "CAL":
            led, *rgb = args
            if not (0 <= led < self.leds and all(0 <= c <= 255 for c in rgb)):
                return E_RANGE, []
            self.gains[led] = (rgb[0], rgb[1], rgb[2])
            return 0, []
        if op == "GO":
            if self.config is None:
                return E_STATE, []
            if args[0] < 0:
                return E_RANGE, []
            self.state, self.fault, self.turns, self.started_s = "SWEEP", "NONE", args[0], now
            return 0, []
        led, *rgb = args  # LED
        if self.state == "SWEEP":
            return E_STATE, []
        if not (0 <= led < self.leds and all(0 <= c <= 255 for c in rgb)):
            return E_RANGE, []
        self.state, self.fault, self.single = "LED", "NONE", (led, rgb[0], rgb[1], rgb[2])
        return 0, []
