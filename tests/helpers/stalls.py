"""Recorders of the torch operations that would stall a GPU's queue, run on the CPU, which dispatches the
same operations: the tests of what a CUDA graph captures and of an epoch that copies nothing from the host."""

from __future__ import annotations

import torch
import torch.utils._pytree as pytree
from torch.utils._python_dispatch import TorchDispatchMode

READS_BACK = {"_local_scalar_dense", "nonzero", "masked_select", "_unique", "_unique2", "unique_dim", "unique_consecutive",
              "repeat_interleave", "is_nonzero", "equal", "allclose", "lift_fresh"}
"""Operations whose result waits for the device (a value read back, or a shape that depends on the data),
and host data made a tensor (``lift_fresh``: on a GPU, a copy from the host): CUDA refuses them while it
captures a graph."""


class ReadsBack(TorchDispatchMode):
    """Within: the names of the READS_BACK operations run, and of the boolean indexing, in ``seen``."""

    def __init__(self) -> None:
        super().__init__()
        self.seen: list[str] = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):  # type: ignore[no-untyped-def]
        name = func.__name__.split(".")[0]
        # a boolean index counts its true entries (a nonzero inside the indexing kernel)
        masked = name.startswith("index") and len(args) > 1 and isinstance(args[1], (list, tuple)) and any(
            isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in args[1])
        if name in READS_BACK or masked:
            self.seen.append(name)
        return func(*args, **(kwargs or {}))


class FromHost(TorchDispatchMode):
    """Within: the names of the operations on ``device``, not the host, that take a tensor of more than one
    element from the host, in ``seen``: on a GPU, a copy from the host's pageable memory, which waits for
    every step queued before it."""

    def __init__(self, device: torch.device) -> None:
        super().__init__()
        self.device, self.seen = device, []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):  # type: ignore[no-untyped-def]
        out = func(*args, **(kwargs or {}))
        tensors = [t for t in pytree.tree_leaves((args, kwargs, out)) if isinstance(t, torch.Tensor)]
        if self.device.type != "cpu" and any(t.device.type == "cpu" and t.dim() > 0 for t in tensors) and \
                any(t.device == self.device for t in tensors):
            self.seen.append(func.__name__.split(".")[0])
        return out
