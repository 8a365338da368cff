"""The Adam loop of DualResPS over eq. 26 (``train``; ``Training`` to stop it and go on), in full
batches or in the mini-batches of spatial tiles the paper's network trains on (``batches.epoch_batches``).

An epoch with ``batch_pixels`` 0 is one full-batch step on all pixels with ``event_batch`` event
pairs drawn at random (0 = all). Otherwise it is a pass over all pixels in mini-batches of about
``batch_pixels`` frame pixels, one Adam step each; on a GPU those steps are replayed as CUDA graphs
(``graphed``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor, nn

from pstoolkit import Progress
from pstoolkit_dualres import graphed
from pstoolkit_dualres.batches import Batch, Tiling, epoch_batches, full_batch
from pstoolkit_dualres.graphed import GraphedSteps
from pstoolkit_dualres.losses import losses
from pstoolkit_dualres.problem import Problem
from pstoolkit_dualres.reflectance import FitModel

# Final learning rate of a stage as a share of its first: an exponential decay over its epochs.
LR_DECAY = 0.1
PROGRESS_EVERY = 10


@dataclass(frozen=True)
class StageConfig:
    """One run of Adam: ``epochs``, learning rates of the surface (``lr``) and of the smooth
    materials (``material_lr``), the loss weights λ_f, λ_e, λ_tv of eq. 26 with the TV term fading
    linearly to zero over the first ``tv_fraction`` of the epochs, ``event_batch`` pairs per step,
    ``batch_pixels``/``tile`` of the mini-batches (0: full batches), the ``seed`` of the draws, and
    whether the mini-batch steps are ``compiled`` (``graphed``)."""

    epochs: int
    lr: float
    material_lr: float
    frame_weight: float
    event_weight: float
    event_huber: float
    indirect_sparsity: float
    tv_weight: float
    tv_fraction: float
    event_batch: int
    batch_pixels: int
    tile: int
    seed: int
    compiled: bool = False


def _event_sample(problem: Problem, config: StageConfig, generator: torch.Generator) -> Tensor:
    """``event_batch`` of the usable pairs at random (all of them at 0), in the pairs' order: grouped by
    super pixel, so that a step reads the pixels' maps in memory order. Drawn on ``generator``'s device,
    the pairs' own."""
    usable = problem.events.usable
    if 0 < config.event_batch < usable.numel():
        chosen = torch.randperm(usable.numel(), generator=generator, device=generator.device)[: config.event_batch]
        return usable[torch.sort(chosen).values]
    return usable


class Training:
    """One stage of Adam on eq. 26 in progress, the learning rates decaying exponentially to ``LR_DECAY``
    of their first over ``config.epochs``: ``run`` goes on to an epoch and may stop before the last, so
    that the solver can set a fit aside, fit something else and come back to it (``interreflection=auto``
    compares two fits early). Its state (the draws' generator, Adam's moments, the schedule, the graphs
    of its steps) is its own; what it fits is ``problem``, ``field`` and ``model`` as they are when it
    runs, which whoever interleaves two trainings puts back (``solver.FitState``).

    Parameters
    ----------
    problem, field, model
        As for ``losses``; the field's parameters and the model's own (if any) are fitted.
    config
        The stage: epochs, learning rates, loss weights, batches and seed.
    progress
        ``progress(fraction, message)``, called at every PROGRESS_EVERY-th epoch and the last.
    before_epoch
        Called with each epoch's index (within the stage) before its batches: what the solver
        re-estimates from the fit as it goes (``thresholds``).

    Attributes
    ----------
    epoch : int
        The epochs run so far.
    history : list of dict
        For every PROGRESS_EVERY-th epoch and the last run: "epoch", "steps" and the loss and its parts,
        means over the epoch's batches.
    """

    def __init__(self, problem: Problem, field: nn.Module, model: FitModel, config: StageConfig, progress: Progress,
                 before_epoch: Callable[[int], None] | None = None) -> None:
        self.problem, self.field, self.model, self.config, self.progress = problem, field, model, config, progress
        self.before_epoch = before_epoch
        self.tiling = Tiling.of(problem) if config.batch_pixels > 0 else None
        # the mini-batches' tiles are drawn on the host (a few thousand integers an epoch); the full batch's
        # event pairs on the problem's device: on a GPU, a copy from the host's pageable memory would wait,
        # once an epoch, for every step queued before it
        draws_on = torch.device("cpu") if self.tiling is not None else problem.device
        self.generator = torch.Generator(device=draws_on).manual_seed(config.seed)
        stepped = graphed.wanted(problem, config.compiled, self.tiling is not None)
        self.optimizer = _adam(field, model, config, problem.device if stepped else None)
        self.steps = GraphedSteps(problem, self.tiling, field, model, config, self.optimizer,
                                  use_graphs=problem.device.type == "cuda") if stepped else None
        self.scheduler = torch.optim.lr_scheduler.ExponentialLR(self.optimizer, LR_DECAY ** (1.0 / max(config.epochs, 1)))
        self.epoch = 0
        self.history: list[dict[str, float]] = []

    def run(self, until: int | None = None) -> None:
        """The epochs from ``epoch`` up to ``until`` (default and at most: ``config.epochs``)."""
        config, problem, generator = self.config, self.problem, self.generator
        until = config.epochs if until is None else min(until, config.epochs)
        warmup = max(config.tv_fraction * config.epochs, 1e-9)
        for epoch in range(self.epoch, until):
            if self.before_epoch is not None:
                self.before_epoch(epoch)
            tv_share = max(0.0, 1.0 - epoch / warmup)
            if self.steps is not None and self.tiling is None:
                totals, count = self.steps.full_epoch(_event_sample(problem, config, generator), tv_share), 1
            elif self.steps is not None:
                padded_epoch = epoch_batches(problem, self.tiling, config.batch_pixels, config.tile, generator)
                totals, count = self.steps.epoch(padded_epoch, tv_share), len(padded_epoch)
            else:
                batches = [full_batch(problem, _event_sample(problem, config, generator))] if self.tiling is None else \
                    epoch_batches(problem, self.tiling, config.batch_pixels, config.tile, generator).batches()
                totals, count = _steps(problem, self.field, self.model, config, self.optimizer, batches, tv_share), len(batches)
            self.scheduler.step()
            self.epoch = epoch + 1
            if epoch % PROGRESS_EVERY == 0 or epoch == config.epochs - 1:
                means = {name: float(value) for name, value in totals.items()}
                self.history.append({"epoch": float(epoch), "steps": float(count), **means})
                self.progress((epoch + 1) / config.epochs, f"epoch {epoch + 1}/{config.epochs} loss {means['loss']:.4g}")

    def close(self) -> None:
        """Free the graphs of its steps (the stage is over, or given up)."""
        if self.steps is not None:
            self.steps.release()


def train(problem: Problem, field: nn.Module, model: FitModel, config: StageConfig, progress: Progress,
          before_epoch: Callable[[int], None] | None = None) -> list[dict[str, float]]:
    """``Training`` (its parameters) run through all ``config.epochs``; its history."""
    training = Training(problem, field, model, config, progress, before_epoch)
    try:
        training.run()
    finally:
        training.close()
    return training.history


def _adam(field: nn.Module, model: FitModel, config: StageConfig, capturable_on: torch.device | None) -> torch.optim.Adam:
    """Adam over the field's surface (at ``config.lr``) and its and the model's materials; with
    ``capturable_on`` a device, capturable by a CUDA graph there and fused (one kernel a group, where
    ``foreach`` takes a dozen), its learning rates tensors on it (a graph reads them where a float
    would be fixed at capture)."""
    def rate(value: float) -> float | Tensor:
        return value if capturable_on is None else torch.tensor(value, device=capturable_on)

    groups: list[dict[str, Any]] = [{"params": field.surface_parameters(), "lr": rate(config.lr)}]
    materials = [*field.material_parameters(), *model.parameters()]
    if materials:
        groups.append({"params": materials, "lr": rate(config.material_lr if field.material_parameters() else config.lr)})
    capturable = capturable_on is not None
    return torch.optim.Adam(groups, capturable=capturable, fused=True if capturable else None)


def _steps(problem: Problem, field: nn.Module, model: FitModel, config: StageConfig, optimizer: torch.optim.Optimizer,
           batches: list[Batch], tv_share: float) -> dict[str, Tensor]:
    """One Adam step per batch, eagerly; the means over the steps of the loss and its parts."""
    totals: dict[str, Tensor] = {}
    for batch in batches:
        # before the losses: the chunked frame term already adds to the model's own gradients
        optimizer.zero_grad(set_to_none=True)
        loss, parts = losses(problem, field, model, config, batch, tv_share)
        loss.backward()
        optimizer.step()
        # kept as tensors: reading a value each step would wait for the device each step
        for name, value in {"loss": loss.detach(), **parts}.items():
            share = value.to(torch.float64) / len(batches)
            totals[name] = totals[name] + share if name in totals else share
    return totals
