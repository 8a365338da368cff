"""What one mini-batch step of the ``paper`` preset costs, on the machine at hand (a proxy for a GPU's
time, which its launches set: issue 36).

On the simulator's ``blobs`` at ``--size`` frame pixels (the problem with the importance samples, the
paper's network at full width, GGX with indirect light, batches of 512 pixels):

- **epoch**: milliseconds to build an epoch's batches (``batches.epoch_batches``): the host's path (numpy),
  and the device's (``batches_device``: torch draws them where the fit runs; here through torch on the
  CPU), and the torch operations the device's path launches to draw and pack an epoch
  (``EpochBatches.packed``; the random draws among them, on the host's generator);
- **ops**: the torch operations of one step's losses and gradient, counted at the dispatcher (views and
  allocations left out; on a GPU each is a kernel launch): the plain batch through torch (as a GPU
  renders it) and the padded one a CUDA graph replays (``graphed``);
- **step**: milliseconds of a step's losses and gradient here: the plain batch through the CPU's compiled
  passes, the padded one eagerly, and with ``--compile`` the padded one through ``torch.compile``
  (its compile time beside it).

    python benchmarks/paper_step.py --size 256 --data /tmp/scale/data
    python benchmarks/paper_step.py --size 256 --compile --out /tmp/paper_step.json
"""

from __future__ import annotations

import argparse
import collections
import platform
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from dualres_scale import capture_path
from results_io import write_results
from torch import nn
from torch.utils._python_dispatch import TorchDispatchMode

import psfmt
from pstoolkit._shared import devices
from pstoolkit.optics.brdf import GGX
from pstoolkit_dualres import losses as loss_module
from pstoolkit_dualres.batches import Tiling, Unpacker, epoch_batches
from pstoolkit_dualres.gather import gather_sum_torch
from pstoolkit_dualres.losses import losses
from pstoolkit_dualres.preprocess import PreprocessOptions, preprocess
from pstoolkit_dualres.presets import PRESETS
from pstoolkit_dualres.problem import Problem, build_problem
from pstoolkit_dualres.reflectance import FitModel
from pstoolkit_dualres.solver import build_field
from pstoolkit_dualres.train import StageConfig

RESULTS = Path(__file__).resolve().parent / "results" / "paper_step.json"
PAPER = PRESETS["paper"]
BATCH_PIXELS = PAPER.batch_pixels
STEPS = 12
# Dispatcher operations that launch no kernel: views, allocations, reads of metadata.
NO_KERNEL = {"view", "as_strided", "t", "transpose", "slice", "expand", "reshape", "detach", "unsqueeze", "select", "permute",
             "_unsafe_view", "alias", "squeeze", "empty", "empty_strided", "empty_like", "_reshape_alias", "lift_fresh", "split",
             "narrow", "unbind", "split_with_sizes", "expand_as", "view_as", "_local_scalar_dense", "is_same_size"}


class _Count(TorchDispatchMode):
    def __init__(self) -> None:
        super().__init__()
        self.ops: collections.Counter[str] = collections.Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):  # type: ignore[no-untyped-def]
        name = func.__name__.split(".")[0]
        if name not in NO_KERNEL:
            self.ops[name] += 1
        return func(*args, **(kwargs or {}))


def milliseconds(run: Callable[[int], Any], count: int) -> float:
    """Mean milliseconds of ``run(i)`` over i = 1 … count − 1, after ``run(0)``."""
    run(0)
    started = time.perf_counter()
    for i in range(1, count):
        run(i)
    return (time.perf_counter() - started) / (count - 1) * 1e3


def setup(path: Path) -> tuple[Problem, nn.Module, FitModel, StageConfig]:
    capture = psfmt.read(path)
    pre = preprocess(capture, PreprocessOptions())
    problem = build_problem(pre, capture.calibration.view_direction, device="cpu", frame_samples=0)
    torch.manual_seed(0)
    model = FitModel(GGX(), indirect=True)
    field = build_field(PAPER, problem, model)
    config = StageConfig(epochs=1, lr=PAPER.lr, material_lr=PAPER.material_lr, frame_weight=1.0, event_weight=PAPER.event_weight,
                         event_huber=0.1, indirect_sparsity=0.05, tv_weight=PAPER.tv_weight, tv_fraction=PAPER.tv_fraction,
                         event_batch=0, batch_pixels=BATCH_PIXELS, tile=8, seed=0)
    return problem, field, model, config


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--compile", action="store_true", help="also time the padded step through torch.compile")
    parser.add_argument("--data", type=Path, help="folder to keep the capture in (default: a temporary one)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        problem, field, model, config = setup(capture_path(args.data or Path(tmp), (args.size, args.size), 0))
    tiling = Tiling.of(problem)
    generator = torch.Generator().manual_seed(0)
    epoch_ms = {"host": milliseconds(lambda i: epoch_batches(problem, tiling, BATCH_PIXELS, 8, generator), 5)}
    epoch = epoch_batches(problem, tiling, BATCH_PIXELS, 8, torch.Generator().manual_seed(1))
    batches, capacity = epoch.batches(), epoch.needs.grown(1.1)
    on_host = devices.on_host
    devices.on_host = lambda device: False
    try:
        epoch_ms["device path"] = milliseconds(lambda i: epoch_batches(problem, tiling, BATCH_PIXELS, 8, generator), 5)
        count = _Count()
        with count:
            epoch_batches(problem, tiling, BATCH_PIXELS, 8, generator).packed(capacity)
    finally:
        devices.on_host = on_host
    epoch_ops = sum(count.ops.values())
    rows, unpack, share = epoch.packed(capacity), Unpacker(capacity, problem.dtype, problem.device), torch.tensor(0.5)

    def plain(i: int) -> None:
        field.zero_grad()
        losses(problem, field, model, config, batches[i % len(batches)], 0.5)[0].backward()

    def padded(i: int) -> None:
        field.zero_grad()
        losses(problem, field, model, config, unpack(rows[i % len(rows)]), share)[0].backward()

    ops: dict[str, dict[str, int]] = {}
    supports, gather = loss_module.supports, loss_module.gather_sum
    # the plain batch rendered and the TV pairs gathered through torch, as on a GPU
    loss_module.supports, loss_module.gather_sum = (lambda model, normal: False), gather_sum_torch
    try:
        for name, step in (("plain batch, torch", plain), ("padded batch", padded)):
            count = _Count()
            with count:
                step(0)
            ops[name] = dict(count.ops.most_common())
    finally:
        loss_module.supports, loss_module.gather_sum = supports, gather
    step_ms = {"plain batch, compiled passes": milliseconds(plain, STEPS), "padded batch, eager": milliseconds(padded, STEPS)}
    record: dict[str, Any] = {
        "benchmark": "paper_step", "size": args.size, "batches": len(epoch), "samples_per_batch": float(np.mean(epoch.rows["samples"])),
        "pairs_per_batch": float(np.mean(epoch.rows["events"])), "capacity": vars(capacity), "epoch_ms": epoch_ms, "epoch_ops": epoch_ops,
        "ops": {name: sum(counts.values()) for name, counts in ops.items()}, "op_names": ops, "step_ms": step_ms,
        "machine": {"torch": torch.__version__, "python": platform.python_version(), "torch_threads": torch.get_num_threads()},
    }
    if args.compile:
        compiled = torch.compile(lambda row: losses(problem, field, model, config, unpack(row), share)[0], fullgraph=True, dynamic=False)
        started = time.perf_counter()
        compiled(rows[0]).backward()
        record["compile_s"] = time.perf_counter() - started

        def compiled_step(i: int) -> None:
            field.zero_grad()
            compiled(rows[i % len(rows)]).backward()

        step_ms["padded batch, torch.compile"] = milliseconds(compiled_step, STEPS)
    print(f"{args.size}²: {len(epoch)} batches an epoch, {record['samples_per_batch']:.0f} samples and "
          f"{record['pairs_per_batch']:.0f} pairs a batch; capacity {vars(capacity)}")
    for name, value in epoch_ms.items():
        print(f"  epoch's batches, {name:<30} {value:8.1f} ms")
    print(f"  epoch's batches drawn and packed on a device: {epoch_ops} operations")
    for name, value in record["ops"].items():
        print(f"  ops of a step, {name:<31} {value:8d}")
    for name, value in step_ms.items():
        print(f"  step, {name:<39} {value:8.1f} ms")
    if "compile_s" in record:
        print(f"  compile {record['compile_s']:.1f} s")
    write_results(args.out, record)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
