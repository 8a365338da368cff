"""Adam steps replayed as CUDA graphs.

A step of the paper's network on 512 pixels launches several hundred small kernels (the MLP, the
rendering of its importance samples and event pairs, their backward, Adam); on a GPU their launches,
not their work, set its time. ``GraphedSteps`` captures one step as a CUDA graph and replays it for
every batch: the step reads its batch from one static row (``batches.EpochBatches.packed``, each field
padded to a ``Capacity``) and the problem's terms from copies the graph owns, so a step costs the copy
of its row and a replay. A full-batch step (the ``fast`` preset) reads the event pairs it draws from a
static row likewise, up to ``FULL_BATCH_PIXELS`` masked pixels (above them its work outweighs its
launches, and a graph would hold its memory for good).

- The largest batches of ``PROBE_EPOCHS`` epochs drawn aside (their counts only), with ``HEADROOM``
  and rounded up (``Capacity.grown``), set the capacities; an epoch with a larger batch grows them
  and captures again.
- The step at which a graph is wanted runs eagerly first (on a side stream, so that capture finds
  every lazy initialisation done), then the graph is captured for the steps after it.
- The problem's terms are copied into the graph's own before each epoch when an ``apply_`` replaced
  them (the thresholds' refit between epochs); a change of shape captures again.
- λ_tv's share is a tensor the graph reads; once it reaches 0, a graph without the TV term.
- Adam runs fused and ``capturable``, its learning rates tensors the scheduler updates in place.
- Each step adds its loss and parts to sums the graph owns; ``epoch`` returns their means.
- A stage's graphs are freed when it ends (``release``), and Python's garbage collector is off while a
  graph is captured: a collection during a capture that destroys another graph (an earlier stage's, a
  finished solve's) makes a call CUDA forbids then, and the capture fails (seen on an H200, now and then).
- A capture that fails is tried again at the next step (the step itself ran eagerly first, so nothing
  is lost); after ``CAPTURE_TRIES`` failures the steps stay eager, with a warning.
- With ``StageConfig.compiled`` (the solver's ``compile``) a mini-batch step's losses go through
  ``torch.compile`` (``COMPILE_BACKEND``, the whole graph, static shapes): elementwise chains fused into
  a few kernels, after a compile of some tens of seconds for each capacity (torch caches it on disk).

Without CUDA (``use_graphs`` False) the same padded steps run eagerly: how the tests hold a padded
step to the step of ``train`` on the same batch, and how ``compiled`` runs on the CPU.
"""

from __future__ import annotations

import dataclasses
import warnings
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor, nn

from pstoolkit._shared import devices
from pstoolkit_dualres.batches import EpochBatches, Tiling, Unpacker, drawn_capacity, full_batch
from pstoolkit_dualres.losses import frame_chunk, losses
from pstoolkit_dualres.problem import Problem
from pstoolkit_dualres.reflectance import FitModel

if TYPE_CHECKING:
    from pstoolkit_dualres.train import StageConfig

# Capacities at least the largest batch of PROBE_EPOCHS epochs drawn aside times HEADROOM: the batches
# of the epochs trained (other offsets and orders of the tiles) rarely outgrow them.
PROBE_EPOCHS = 4
HEADROOM = 1.1
# Failed captures of one stage's step before its steps stay eager.
CAPTURE_TRIES = 3
# What compiles a step's losses where ``StageConfig.compiled`` asks (the tests trace with aot_eager).
COMPILE_BACKEND = "inductor"
# The most masked pixels whose full-batch steps are replayed as graphs.
FULL_BATCH_PIXELS = 1 << 19
# The terms of the problem a step reads, which the graph keeps its own copies of.
FRAME_TERMS = ("shared_light", "shared_weight", "shared_visible", "sample_light", "sample_weight", "measured", "saturated",
               "energy")
EVENT_TERMS = ("taps", "tap_weight_now", "tap_weight_ref", "light_now", "light_ref", "tap_area", "grey_now", "grey_ref",
               "target", "weight")


def wanted(problem: Problem, compiled: bool, mini_batches: bool) -> bool:
    """Whether ``train`` steps through ``GraphedSteps``: ``mini_batches`` on CUDA or ``compiled``, full
    batches on CUDA up to FULL_BATCH_PIXELS masked pixels."""
    cuda = problem.device.type == "cuda"
    if mini_batches:
        return cuda or compiled
    return cuda and problem.geometry.pixels.size <= FULL_BATCH_PIXELS


class _Terms:
    """The graph's own copies of the problem's terms (``problem``: the problem with them in place) and
    the tensors they were copied from."""

    def __init__(self, problem: Problem) -> None:
        self.frames = {name: getattr(problem.frames, name) for name in FRAME_TERMS}
        self.events = {name: getattr(problem.events, name) for name in EVENT_TERMS}
        self.problem = dataclasses.replace(
            problem,
            frames=dataclasses.replace(problem.frames, **{k: _copy(v) for k, v in self.frames.items()}),
            events=dataclasses.replace(problem.events, **{k: _copy(v) for k, v in self.events.items()}))

    def refresh(self, problem: Problem) -> bool:
        """Copy the problem's terms replaced since into the graph's own; False where one changed its
        shape, dtype or presence (the graph must be captured again, on new copies)."""
        for source, store, own in ((problem.frames, self.frames, self.problem.frames), (problem.events, self.events, self.problem.events)):
            for name, was in store.items():
                now = getattr(source, name)
                if now is was:
                    continue
                kept = getattr(own, name)
                if now is None or kept is None or now.shape != kept.shape or now.dtype != kept.dtype:
                    return False
                kept.copy_(now)
                store[name] = now
        return True


def _copy(value: Tensor | None) -> Tensor | None:
    return None if value is None else value.clone()


class GraphedSteps:
    """The steps of one stage of ``train`` (module docstring): ``epoch`` of mini-batches, or
    ``full_epoch``.

    Parameters
    ----------
    problem, field, model, config
        As for ``losses``; the problem's terms are copied.
    tiling
        The problem's ``batches.Tiling``, which the mini-batch epochs are drawn from; None: full
        batches.
    optimizer
        Adam over the field's and the model's parameters: ``capturable`` with tensor learning rates
        where ``use_graphs``.
    use_graphs
        Capture and replay CUDA graphs (the problem on a CUDA device); else every step runs eagerly.
    """

    def __init__(self, problem: Problem, tiling: Tiling | None, field: nn.Module, model: FitModel, config: StageConfig,
                 optimizer: torch.optim.Optimizer, use_graphs: bool) -> None:
        self.problem, self.field, self.model, self.config, self.optimizer = problem, field, model, config, optimizer
        self.use_graphs = use_graphs
        self.failed_captures = 0
        self.terms = _Terms(problem)
        self.graphs: dict[bool, Any] = {}
        self.sums: dict[str, Tensor] = {}
        self.names: dict[bool, list[str]] = {}
        self.tv_share = torch.zeros((), dtype=problem.dtype, device=problem.device)
        if tiling is None:
            self.row = torch.zeros(0, dtype=torch.int64, device=problem.device)
            # found once, outside any capture: the device's free memory is no question to ask in one
            grid = problem.frames.shared_light
            self.frame_chunk = frame_chunk(self.tv_share, 0 if grid is None else grid.shape[0])
            # a frame term in several chunks differentiates each inside the step: left to eager steps
            self.use_graphs = use_graphs and (grid is None or problem.geometry.pixels.size <= self.frame_chunk)
            self.losses = self._full_losses
            return
        # the same draws for every stage: stages whose masks keep the same batches share the capacities
        aside = torch.Generator().manual_seed(0)
        self.capacity = drawn_capacity(problem, tiling, config.batch_pixels, config.tile, aside, PROBE_EPOCHS).grown(HEADROOM)
        self._set_rows()
        self.losses = torch.compile(self._losses, backend=COMPILE_BACKEND, fullgraph=True, dynamic=False) \
            if config.compiled else self._losses

    def epoch(self, batches: EpochBatches, tv_share: float) -> dict[str, Tensor]:
        """One Adam step per batch of ``batches`` at λ_tv's share ``tv_share``; the means over the
        steps of the loss and its parts (float64 0-dim tensors on the device, as ``train`` keeps them)."""
        needed = batches.needs
        if not self.capacity.covers(needed):
            self.capacity = self.capacity.union(needed.grown(HEADROOM))
            self._set_rows()
            self.graphs.clear()
        return self._run(batches.packed(self.capacity), tv_share)

    def full_epoch(self, events: Tensor, tv_share: float) -> dict[str, Tensor]:
        """One full-batch Adam step on the event pairs ``events`` (indices into all pairs), as ``epoch``."""
        if self.row.shape != events.shape:
            self.row = torch.empty_like(events)
            self.graphs.clear()
        return self._run(events[None], tv_share)

    def release(self) -> None:
        """Free the graphs (the stage is over): now, by their count of references, and not when a garbage
        collection reaches them, which may be during a later capture."""
        self.graphs.clear()

    def _run(self, rows: Tensor, tv_share: float) -> dict[str, Tensor]:
        """One step per row of ``rows`` (each copied into ``row``), as ``epoch``."""
        if not self.terms.refresh(self.problem):
            self.terms = _Terms(self.problem)
            self.graphs.clear()
        tv_on = tv_share > 0 and self.config.tv_weight > 0
        if not tv_on:
            # the share only falls within a stage: the graph with the term will not replay again, free its memory
            self.graphs.pop(True, None)
        self.tv_share.fill_(tv_share)
        for value in self.sums.values():
            value.zero_()
        for b in range(len(rows)):
            self.row.copy_(rows[b])
            graph = self.graphs.get(tv_on)
            if graph is not None:
                graph.replay()
                continue
            self._eager(tv_on)
            if self.use_graphs:
                try:
                    self.graphs[tv_on] = self._capture(tv_on)
                except RuntimeError as error:
                    # what capture refuses (an operation a later torch syncs on) costs speed, not the fit
                    self.failed_captures += 1
                    if self.failed_captures >= CAPTURE_TRIES:
                        warnings.warn(f"dualres: a CUDA graph of the training step could not be captured in "
                                      f"{CAPTURE_TRIES} tries, the steps run eagerly: {error}", RuntimeWarning, stacklevel=2)
                        self.use_graphs = False
        return {name: self.sums[name] / max(len(rows), 1) for name in self.names.get(tv_on, [])}

    def _set_rows(self) -> None:
        """The static row and its unpacker for the capacities now."""
        self.row = torch.zeros(self.capacity.width, dtype=torch.int64, device=self.problem.device)
        self.unpack = Unpacker(self.capacity, self.problem.dtype, self.problem.device)

    def _step(self, tv_on: bool) -> None:
        """The step on the batch in ``row``: the losses, their gradient, Adam, the sums."""
        loss, parts = self.losses(self.row, self.tv_share if tv_on else 0.0)
        loss.backward()
        self.optimizer.step()
        values = {"loss": loss.detach(), **parts}
        self.names[tv_on] = list(values)
        for name, value in values.items():
            if name not in self.sums:
                self.sums[name] = torch.zeros((), dtype=torch.float64, device=value.device)
            self.sums[name].add_(value.to(torch.float64))

    def _losses(self, row: Tensor, tv_share: float | Tensor) -> tuple[Tensor, dict[str, Tensor]]:
        """``losses`` of the batch packed in ``row``."""
        return losses(self.terms.problem, self.field, self.model, self.config, self.unpack(row), tv_share)

    def _full_losses(self, events: Tensor, tv_share: float | Tensor) -> tuple[Tensor, dict[str, Tensor]]:
        """``losses`` of the full batch with the event pairs ``events``."""
        batch = full_batch(self.terms.problem, events, self.frame_chunk)
        return losses(self.terms.problem, self.field, self.model, self.config, batch, tv_share)

    def _eager(self, tv_on: bool) -> None:
        self.optimizer.zero_grad(set_to_none=True)
        if not self.use_graphs:
            self._step(tv_on)
            return
        side = torch.cuda.Stream()
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side):
            self._step(tv_on)
        torch.cuda.current_stream().wait_stream(side)

    def _capture(self, tv_on: bool) -> Any:
        # the graph's backward makes the gradients in its own memory, which later replays write
        self.optimizer.zero_grad(set_to_none=True)
        graph = torch.cuda.CUDAGraph()
        with devices.collector_off(), torch.cuda.graph(graph):
            self._step(tv_on)
        return graph
