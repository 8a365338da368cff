"""Where a computation that has a torch copy for devices runs, and what a capture of one as a CUDA graph needs."""

from __future__ import annotations

import contextlib
import gc
from collections.abc import Iterator


def on_host(device: object) -> bool:
    """Whether ``device`` (a torch device or its name) is the CPU, where the host's numpy and numba code
    runs; elsewhere its torch copy runs on the device (the closed form's iteration, the surface's
    integration and shadow sweep). Called through this module, so a test can send the CPU down the
    device's path."""
    return str(device).split(":")[0] == "cpu"


def memory_budget(device: object, cap_bytes: int, share: float = 0.25) -> int:
    """Bytes a batch of work on ``device`` may take: ``cap_bytes``, or on a CUDA device that share of
    its free memory when less (a smaller card, or one the fit already fills), at least 64 MiB."""
    import torch  # deferred: only a device's work asks

    device = torch.device(device)
    if device.type != "cuda":
        return cap_bytes
    free_bytes, _ = torch.cuda.mem_get_info(device)
    return int(max(64 << 20, min(cap_bytes, share * free_bytes)))


@contextlib.contextmanager
def collector_off() -> Iterator[None]:
    """Python's garbage collector off for the block, as it was after: around a CUDA graph's capture, where a
    collection that destroys another graph makes a call CUDA forbids then, and the capture fails."""
    collecting = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if collecting:
            gc.enable()
