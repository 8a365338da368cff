"""The ring-light serial protocol (``spec/ringlight-protocol.md``): frames, checksum, codes.

A frame is one ASCII line ``<start><body>*<crc>\\n``: start ``#`` from the host, ``!`` from the device;
the body is space-separated words; ``crc`` is the CRC-8/SMBUS of the body as two upper-case hex digits.
Requests are ``ID OP ARGS…``, replies ``ID OK FIELDS…`` or ``ID ER CODE``, where ID is two hex digits.
"""

from __future__ import annotations

from dataclasses import dataclass

PROTOCOL_VERSION = 1
FIRMWARE_NAME = "pstoolkit-ringlight"
REQUEST = "#"
REPLY = "!"
MAX_LINE = 64
NO_ID = "--"

ERRORS: dict[int, str] = {
    1: "bad checksum",
    2: "malformed request",
    3: "unknown command",
    4: "argument out of range",
    5: "not allowed in the current state",
    6: "line too long",
}
E_CRC, E_SYNTAX, E_UNKNOWN, E_RANGE, E_STATE, E_LONG = range(1, 7)
TRIGGERS = {"off": 0, "period": 1, "exposure": 2}


class ProtocolError(ValueError):
    """A line that is not a valid frame (garbage, a bad checksum, a wrong start byte)."""


def _crc_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x07) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
        table.append(crc)
    return tuple(table)


_TABLE = _crc_table()


def crc8(data: bytes) -> int:
    """CRC-8/SMBUS: polynomial 0x07, initial value 0, no reflection, no final xor ("123456789" → 0xF4)."""
    crc = 0
    for byte in data:
        crc = _TABLE[crc ^ byte]
    return crc


def encode(start: str, words: list[str]) -> bytes:
    """A frame of ``words`` with the start character and checksum."""
    body = " ".join(words).encode("ascii")
    return f"{start}".encode() + body + f"*{crc8(body):02X}\n".encode()


def decode(line: bytes, start: str) -> list[str]:
    """The words of a frame that begins with ``start``; ProtocolError for anything else."""
    text = line.rstrip(b"\r\n")
    if len(text) > MAX_LINE:
        raise ProtocolError(f"line of {len(text)} bytes exceeds {MAX_LINE}")
    if not text.startswith(start.encode()) or b"*" not in text:
        raise ProtocolError(f"not a frame: {_shown(line)}")
    body, _, crc_hex = text[1:].rpartition(b"*")
    try:
        crc = int(crc_hex, 16)
        words = body.decode("ascii").split(" ")
    except (ValueError, UnicodeDecodeError):
        raise ProtocolError(f"not a frame: {_shown(line)}") from None
    if len(crc_hex) != 2 or crc != crc8(body):
        raise ProtocolError(f"bad checksum in {_shown(line)}")
    if not all(words):
        raise ProtocolError(f"empty word in {_shown(line)}")
    return words


def _shown(line: bytes) -> str:
    return repr(line[:24]) + ("…" if len(line) > 24 else "")


def request(request_id: int, op: str, *args: int) -> bytes:
    return encode(REQUEST, [f"{request_id & 0xFF:02X}", op, *(str(int(a)) for a in args)])


@dataclass(frozen=True)
class Reply:
    """A decoded reply: the request id it answers, ``ok``, its fields, or the error code."""

    request_id: str
    ok: bool
    fields: tuple[str, ...] = ()
    code: int = 0

    @property
    def error(self) -> str:
        return ERRORS.get(self.code, f"error {self.code}")


def parse_reply(line: bytes) -> Reply:
    words = decode(line, REPLY)
    if len(words) < 2 or words[1] not in ("OK", "ER"):
        raise ProtocolError(f"not a reply: {_shown(line)}")
    if words[1] == "OK":
        return Reply(words[0], True, tuple(words[2:]))
    try:
        return Reply(words[0], False, code=int(words[2]))
    except (IndexError, ValueError):
        raise ProtocolError(f"error reply without a code: {_shown(line)}") from None
