"""The host side of the ring-light protocol over pyserial: open, handshake, request with deadline,
bounded retries and reconnects, and one-line errors that name the port."""

from __future__ import annotations

import errno
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import serial

from pstoolkit import UserError
from pstoolkit_ringlight.protocol import (
    E_CRC,
    FIRMWARE_NAME,
    MAX_LINE,
    PROTOCOL_VERSION,
    ProtocolError,
    parse_reply,
    request,
)

SIM_URL = "ringlightsim://"


class DeviceError(UserError):
    """The ring light is missing, refuses, answers garbage or stops answering; one line naming the port."""


@dataclass(frozen=True)
class DeviceInfo:
    firmware: str
    version: str
    leds: int
    protocol: int


def port_url(port: str) -> str:
    """``sim`` (or ``sim?leds=24``) is the simulated device; anything else goes to pyserial as is
    (a device path, ``COM3``, or a URL such as ``rfc2217://host:port``)."""
    if port == "sim" or port.startswith("sim?"):
        return SIM_URL + port
    return port


def _reason(exc: Exception) -> str:
    """The first line of an exception's message, without the ``[Errno N]`` prefix."""
    text = str(getattr(exc, "strerror", None) or exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def _open_error(port: str, exc: serial.SerialException) -> DeviceError:
    code = getattr(exc, "errno", None)
    if code == errno.ENOENT:
        return DeviceError(f"ring light port {port}: no such device (is it plugged in? list ports with `python -m serial.tools.list_ports`)")
    if code in (errno.EACCES, errno.EPERM):
        return DeviceError(f"ring light port {port}: permission denied (on Linux add yourself to the 'dialout' group)")
    if code == errno.EBUSY:
        return DeviceError(f"ring light port {port}: busy (another program has it open)")
    return DeviceError(f"ring light port {port}: cannot open ({_reason(exc)})")


class RingLightClient:
    """Talks to one controller. ``timeout_s`` is the reply deadline of one try; a request is tried
    ``1 + retries`` times (same request id, so the device never acts twice) and a lost connection
    is reopened up to ``reconnects`` times."""

    def __init__(
        self,
        port: str,
        *,
        timeout_s: float = 0.2,
        retries: int = 3,
        reconnects: int = 2,
        baudrate: int = 115200,
        opener: Callable[..., Any] = serial.serial_for_url,
    ) -> None:
        self.port = port
        self.timeout_s = timeout_s
        self.retries = retries
        self.reconnects = reconnects
        self.baudrate = baudrate
        self._opener = opener
        self._serial: Any = None
        self._next_id = 0
        self.info: DeviceInfo | None = None
        self.reopened = 0

    def connect(self) -> DeviceInfo:
        """Open the port and check that the far end is this protocol's firmware."""
        try:
            self._serial = self._opener(port_url(self.port), baudrate=self.baudrate, timeout=self.timeout_s, write_timeout=self.timeout_s)
        except serial.SerialException as exc:
            raise _open_error(self.port, exc) from None
        except ValueError as exc:
            raise DeviceError(f"ring light port {self.port}: {exc}") from None
        self.info = self.identify()
        return self.info

    def identify(self) -> DeviceInfo:
        fields = self.request("ID")
        try:
            firmware, version, leds, protocol = fields[0], fields[1], int(fields[2]), int(fields[3])
        except (IndexError, ValueError):
            raise DeviceError(f"ring light on {self.port}: identity reply {' '.join(fields)!r} is not 'FIRMWARE VERSION LEDS PROTOCOL'") from None
        if firmware != FIRMWARE_NAME or protocol != PROTOCOL_VERSION:
            raise DeviceError(
                f"ring light on {self.port}: wrong firmware {firmware} {version} (protocol {protocol}); "
                f"expected {FIRMWARE_NAME} with protocol {PROTOCOL_VERSION} (flash examples/firmware/ringlight)"
            )
        if leds < 1:
            raise DeviceError(f"ring light on {self.port}: the device reports {leds} LEDs")
        return DeviceInfo(firmware, version, leds, protocol)

    def close(self) -> None:
        if self._serial is not None:
            try:
                self._serial.close()
            except (serial.SerialException, OSError):
                pass
            self._serial = None

    def _reopen(self, op: str) -> None:
        self.close()
        try:
            self._serial = self._opener(port_url(self.port), baudrate=self.baudrate, timeout=self.timeout_s, write_timeout=self.timeout_s)
        except (serial.SerialException, ValueError) as exc:
            raise DeviceError(f"ring light on {self.port}: connection lost during {op} and the port cannot be reopened ({_reason(exc)})") from None
        self.reopened += 1

    def _exchange(self, frame: bytes) -> bytes:
        self._serial.reset_input_buffer()
        self._serial.write(frame)
        return bytes(self._serial.read_until(b"\n", MAX_LINE + 2))

    def request(self, op: str, *args: int) -> list[str]:
        """Send one command and return the fields of its OK reply. DeviceError when the device
        refuses it, answers only garbage, stays silent through every try, or is gone for good."""
        if self._serial is None:
            raise DeviceError(f"ring light on {self.port}: not connected")
        request_id = f"{self._next_id:02X}"
        frame = request(self._next_id, op, *args)
        self._next_id = (self._next_id + 1) & 0xFF
        garbage: bytes | None = None
        reconnects = 0
        tries = 0
        while tries <= self.retries:
            try:
                line = self._exchange(frame)
            except (serial.SerialException, OSError) as exc:
                if reconnects >= self.reconnects:
                    raise DeviceError(f"ring light on {self.port}: connection lost during {op} ({_reason(exc)})") from None
                reconnects += 1
                self._reopen(op)
                continue
            tries += 1
            if not line.endswith(b"\n"):
                if line:
                    garbage = line
                continue
            try:
                reply = parse_reply(line)
            except ProtocolError:
                garbage = line
                continue
            if not reply.ok and reply.code == E_CRC:
                continue
            if reply.request_id != request_id:
                garbage = line
                continue
            if not reply.ok:
                raise DeviceError(f"ring light on {self.port}: {op} {' '.join(map(str, args))}".rstrip() + f" refused: {reply.error} (code {reply.code})")
            return list(reply.fields)
        if garbage is not None:
            raise DeviceError(f"ring light on {self.port}: answers garbage, not the ring-light protocol (last reply {garbage[:24]!r}); "
                              "wrong port or baud rate?")
        raise DeviceError(f"ring light on {self.port}: no reply to {op} within {self.timeout_s * 1000:.0f} ms after {self.retries + 1} tries")
