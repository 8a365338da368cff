"""pstoolkit — the photometric-stereo core: plugins and registries, shared maths, simulator, CLI."""

from __future__ import annotations

__version__ = "0.1.0"
