"""First-party plugin: the ``replay`` camera source that plays a capture file as if it were the rig."""

from __future__ import annotations

from pstoolkit import Registry, hookimpl


@hookimpl
def pstoolkit_register_backends(registry: Registry) -> None:
    from pstoolkit_replay.source import Replay

    registry.register(Replay)
