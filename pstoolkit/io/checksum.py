"""SHA-256 of a file, read in bounded chunks: what ``result.json`` records of the capture a run read
(``capture_sha256``), so that ``pstoolkit run --config result.json`` can tell the same file from a
changed one."""

from __future__ import annotations

import hashlib
from pathlib import Path

CHUNK_BYTES = 1 << 20
"""Bytes read at a time: memory stays at one chunk whatever the file's size."""


def file_sha256(path: Path) -> str:
    """The SHA-256 of the file at ``path`` as 64 lowercase hex digits. OSError when it cannot be read."""
    digest = hashlib.sha256()
    with open(path, "rb") as stream:
        while chunk := stream.read(CHUNK_BYTES):
            digest.update(chunk)
    return digest.hexdigest()
