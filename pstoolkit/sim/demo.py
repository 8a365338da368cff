"""The built-in demo capture that ``pstoolkit run`` uses when no capture is given.

It is simulated on first use with fixed options (``DEMO_CONFIG``: the ``blobs`` scene, 128×128
frames, three long exposures and events at half resolution over one light period, seed 0) and
cached as ``demo-<key>.h5`` under ``$XDG_CACHE_HOME/pstoolkit`` (default ``~/.cache/pstoolkit``).
The key hashes the options, the pstoolkit version and the format version, so a new release makes a
new file. The capture is written atomically, so concurrent first runs are safe: each writes its own
temporary file and the last rename wins with identical data.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import asdict
from pathlib import Path

import psfmt
from pstoolkit._shared.progress import Progress, no_progress
from pstoolkit.errors import UserError
from pstoolkit.sim.config import SimulationConfig
from pstoolkit.sim.simulator import simulate
from pstoolkit.version import __version__

DEMO_CONFIG = SimulationConfig(scene="blobs", size=128, seed=0, event_scale=0.5, frames=3, periods=1)


def cache_dir() -> Path:
    """``$XDG_CACHE_HOME/pstoolkit``, or ``~/.cache/pstoolkit`` when the variable is unset or empty."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "pstoolkit"


def demo_key(config: SimulationConfig) -> str:
    """16 hex digits identifying the demo's content: options, pstoolkit and format versions."""
    text = json.dumps(
        {"config": asdict(config), "pstoolkit": __version__, "format": psfmt.FORMAT_VERSION_STR},
        sort_keys=True,
    )
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def demo_capture_path(config: SimulationConfig = DEMO_CONFIG, progress: Progress = no_progress) -> Path:
    """The cached demo capture, simulated first if it is not there yet."""
    path = cache_dir() / f"demo-{demo_key(config)}.h5"
    if path.is_file():
        return path
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"{path.parent}: cannot create the cache folder for the demo capture ({exc.strerror})") from None
    simulate(config, path, progress)
    return path
