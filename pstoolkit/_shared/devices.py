"""Where a computation that has a torch copy for devices runs."""

from __future__ import annotations


def on_host(device: object) -> bool:
    """Whether ``device`` (a torch device or its name) is the CPU, where the host's numpy and numba code
    runs; elsewhere its torch copy runs on the device (the closed form's iteration, the surface's
    integration and shadow sweep). Called through this module, so a test can send the CPU down the
    device's path."""
    return str(device).split(":")[0] == "cpu"
