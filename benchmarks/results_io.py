"""Writing a benchmark's JSON table, shared by every script in this folder."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import psfmt


def write_results(path: Path, result: dict[str, Any]) -> None:
    """Write ``result`` as indented JSON to ``path`` atomically, creating its folder."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with psfmt.atomic_path(path) as tmp:
        tmp.write_text(json.dumps(result, indent=2) + "\n")
