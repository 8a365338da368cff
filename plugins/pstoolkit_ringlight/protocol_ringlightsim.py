"""pyserial URL handler ``ringlightsim://NAME?options``: a serial port wired to a simulated ring light.

pyserial finds it through ``serial.protocol_handler_packages`` (the plugin appends its package), so
``serial.serial_for_url("ringlightsim://bench?leds=24")`` opens a port whose far end runs
``SimulatedRingLight``. Devices live per NAME for the life of the process, so a reconnect finds the
same device and a test can look at it (``device(NAME)``). Options, used when NAME is first opened:
``leds``, ``firmware``, ``version``, ``protocol``, and faults ``drop=3,5``, ``corrupt=2``,
``blip=4``, ``garbage=1``, ``disconnect=N``, ``reset=1`` (see ``Faults``).
"""

from __future__ import annotations

import errno
import time
import urllib.parse

from serial.serialutil import PortNotOpenError, SerialBase, SerialException

from pstoolkit_ringlight.device import Faults, SimulatedRingLight

SCHEME = "ringlightsim"
_DEVICES: dict[str, SimulatedRingLight] = {}


def device(name: str) -> SimulatedRingLight:
    """The simulated device behind ``ringlightsim://NAME`` (KeyError if never opened)."""
    return _DEVICES[name]


def _numbers(values: list[str]) -> set[int]:
    return {int(v) for value in values for v in value.split(",") if v}


def _make_device(query: str) -> SimulatedRingLight:
    params = urllib.parse.parse_qs(query, keep_blank_values=True)
    known = {"leds", "firmware", "version", "protocol", "drop", "corrupt", "blip", "garbage", "disconnect", "reset"}
    unknown = sorted(set(params) - known)
    if unknown:
        raise ValueError(f"unknown option(s) {', '.join(unknown)} (known: {', '.join(sorted(known))})")
    first = {k: v[-1] for k, v in params.items()}
    faults = Faults(
        drop=_numbers(params.get("drop", [])),
        corrupt=_numbers(params.get("corrupt", [])),
        blip=_numbers(params.get("blip", [])),
        garbage=first.get("garbage", "0") not in ("", "0"),
        reset=first.get("reset", "0") not in ("", "0"),
        disconnect=int(first.get("disconnect", 0)),
    )
    kwargs: dict[str, object] = {"faults": faults}
    if "leds" in first:
        kwargs["leds"] = int(first["leds"])
    if "protocol" in first:
        kwargs["protocol"] = int(first["protocol"])
    for key in ("firmware", "version"):
        if key in first:
            kwargs[key] = first[key]
    return SimulatedRingLight(**kwargs)  # type: ignore[arg-type]


class Serial(SerialBase):
    """The port: each line written is handed to the device, its answer waits to be read."""

    def open(self) -> None:
        if self._port is None:
            raise SerialException("Port must be configured before it can be used.")
        if self.is_open:
            raise SerialException("Port is already open.")
        parts = urllib.parse.urlsplit(self._port)
        if parts.scheme != SCHEME:
            raise SerialException(f"expected {SCHEME}://NAME?options, got {self._port!r}")
        name = parts.netloc or "sim"
        if name not in _DEVICES:
            try:
                _DEVICES[name] = _make_device(parts.query)
            except ValueError as exc:
                raise SerialException(f"{self._port}: {exc}") from None
        self._device = _DEVICES[name]
        if self._device.disconnected:
            raise SerialException(errno.ENOENT, f"could not open port {self._port}: [Errno 2] No such file or directory")
        if self._device.faults.reset:
            self._device.restart()
        self._rx = bytearray()
        self._tx = bytearray()
        self._broken = False
        self.is_open = True

    def close(self) -> None:
        self.is_open = False

    def _reconfigure_port(self) -> None:
        """Baud rate and framing mean nothing to a simulated wire."""

    def _check(self) -> None:
        if not self.is_open:
            raise PortNotOpenError()
        if self._broken or self._device.disconnected:
            raise SerialException("device reports readiness to read but returned no data (device disconnected or multiple access on port?)")

    @property
    def in_waiting(self) -> int:
        self._check()
        return len(self._rx)

    def read(self, size: int = 1) -> bytes:
        self._check()
        if not self._rx and self._timeout:
            time.sleep(self._timeout)  # nothing will come: the caller waits its timeout, as on a wire
        data = bytes(self._rx[:size])
        del self._rx[:size]
        return data

    def write(self, data: bytes) -> int:
        self._check()
        self._tx += data
        while b"\n" in self._tx:
            line, _, rest = bytes(self._tx).partition(b"\n")
            self._tx = bytearray(rest)
            self._rx += self._device.receive(line.rstrip(b"\r"))
            self._broken = self._device.requests in self._device.faults.blip
        return len(data)

    def reset_input_buffer(self) -> None:
        self._check()
        self._rx.clear()

    def reset_output_buffer(self) -> None:
        self._check()
        self._tx.clear()
