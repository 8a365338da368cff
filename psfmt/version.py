"""Format identity and version rules (spec/hybrid-capture.md §2)."""

from __future__ import annotations

FORMAT_NAME = "hybrid-capture"
FORMAT_VERSION = (1, 3)
FORMAT_VERSION_STR = f"{FORMAT_VERSION[0]}.{FORMAT_VERSION[1]}"


def parse_version(text: str) -> tuple[int, int]:
    """``"1.3"`` → ``(1, 3)``; raises ValueError on anything else."""
    parts = str(text).strip().split(".")
    if len(parts) != 2 or not all(p.isdigit() for p in parts):
        raise ValueError(f"format_version {text!r} is not MAJOR.MINOR")
    return int(parts[0]), int(parts[1])


def is_readable(version: tuple[int, int]) -> bool:
    """A reader of this version reads any file of the same major; a newer minor only adds optional parts."""
    return version[0] == FORMAT_VERSION[0]
