"""PNG files checked before decoding: structure, checksums and header (size, bit depth, channels).

Walking the chunks and verifying every CRC catches truncated and corrupted files with a precise
message and without handing them to the decoder, which may print its own complaints on stderr.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pstoolkit import UserError
from pstoolkit.io.normalmap import decode_image

SIGNATURE = b"\x89PNG\r\n\x1a\n"
CHANNELS = {0: 1, 2: 3, 3: 3, 4: 2, 6: 4}
"""PNG colour type → channels as decoded (a palette image decodes to RGB)."""


@dataclass(frozen=True)
class PngHeader:
    width: int
    height: int
    bit_depth: int
    channels: int


def check_png(path: Path) -> PngHeader:
    """The header of a structurally sound PNG; UserError naming ``path`` when the file is missing,
    not a PNG, truncated or has a chunk whose checksum does not match."""
    if not path.is_file():
        raise UserError(f"{path}: file does not exist")
    data = memoryview(path.read_bytes())
    if data[:8] != SIGNATURE:
        raise UserError(f"{path}: not a PNG file")
    pos, header = 8, None
    while True:
        if pos + 12 > len(data):
            raise UserError(f"{path}: corrupted PNG (truncated, no IEND chunk)")
        length, kind = struct.unpack(">I4s", data[pos : pos + 8])
        end = pos + 12 + length
        if end > len(data):
            raise UserError(f"{path}: corrupted PNG (truncated in chunk {kind.decode('latin-1')!r})")
        (crc,) = struct.unpack(">I", data[end - 4 : end])
        if zlib.crc32(data[pos + 4 : end - 4]) != crc:
            raise UserError(f"{path}: corrupted PNG (checksum mismatch in chunk {kind.decode('latin-1')!r})")
        if header is None:
            if kind != b"IHDR" or length != 13:
                raise UserError(f"{path}: corrupted PNG (no IHDR header chunk)")
            width, height, depth, colour = struct.unpack(">IIBB", data[pos + 8 : pos + 18])
            if colour not in CHANNELS:
                raise UserError(f"{path}: corrupted PNG (unknown colour type {colour})")
            header = PngHeader(width, height, depth, CHANNELS[colour])
        if kind == b"IEND":
            return header
        pos = end


def decode(path: Path) -> np.ndarray:
    """The image as stored (OpenCV order: BGR for colour), at its own bit depth."""
    image = decode_image(path)
    if image is None:
        raise UserError(f"{path}: corrupted PNG (the image data cannot be decoded)")
    return image
