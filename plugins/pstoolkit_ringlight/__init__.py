"""First-party plugin: the serial ring-light hardware backend (``ringlight``).

Also makes the simulated controller reachable through pyserial as ``ringlightsim://NAME``
(``--port sim``), by adding this package to ``serial.protocol_handler_packages``.
"""

from __future__ import annotations

import serial

from pstoolkit import Registry, hookimpl

if __name__ not in serial.protocol_handler_packages:
    serial.protocol_handler_packages.append(__name__)


@hookimpl
def pstoolkit_register_backends(registry: Registry) -> None:
    from pstoolkit_ringlight.backend import RingLightBackend

    registry.register(RingLightBackend)
