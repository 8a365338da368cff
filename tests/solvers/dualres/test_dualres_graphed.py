"""The paper preset's steps as a GPU replays them (``graphed``): an epoch's batches packed into rows of
one size and unpacked again, a padded step's losses and gradients equal to its batch's own, and a stage
of padded steps training as the plain one; on a GPU, CUDA graphs replaying those steps as they run
eagerly (``pytest -m cuda``)."""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import functools
import gc
import warnings
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from helpers.stalls import FromHost, ReadsBack

import psfmt
from pstoolkit._shared.progress import no_progress
from pstoolkit.optics.brdf import GGX
from pstoolkit.shadows.score import true_shadows
from pstoolkit_dualres import gather, graphed
from pstoolkit_dualres import losses as losses_module
from pstoolkit_dualres.batches import Capacity, Tiling, Unpacker, drawn_capacity, epoch_batches, full_batch
from pstoolkit_dualres.fields import NeuralField
from pstoolkit_dualres.losses import losses
from pstoolkit_dualres.preprocess import PreprocessOptions, preprocess
from pstoolkit_dualres.presets import PRESETS
from pstoolkit_dualres.problem import Problem, build_problem
from pstoolkit_dualres.reflectance import FitModel
from pstoolkit_dualres.solver import build_field, deterministic
from pstoolkit_dualres.train import StageConfig, Training, train

STAGE = StageConfig(epochs=3, lr=1e-3, material_lr=1e-3, frame_weight=1.0, event_weight=0.05, event_huber=0.1,
                    indirect_sparsity=0.01, tv_weight=0.02, tv_fraction=0.5, event_batch=0, batch_pixels=200, tile=8, seed=0)


def _problem(path: Path, device: str = "cpu", frame_samples: int = 0) -> Problem:
    """The blobs' problem with the importance samples (or ``frame_samples`` a frame on a shared grid),
    under their true cast shadows."""
    capture = psfmt.read(path)
    pre = preprocess(capture, PreprocessOptions())
    problem = build_problem(pre, capture.calibration.view_direction, device=device, frame_samples=frame_samples)
    gt = capture.ground_truth
    problem.apply_mask(true_shadows(gt.depth, gt.mask, pre.light, pre.t0_us, pre.period_us))
    return problem


@pytest.fixture(scope="module")
def blobs(blobs_48: Path) -> Problem:
    return _problem(blobs_48)


def _angle_deg(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(N,) angles between unit rows, in float64 through atan2 (arccos resolves 0.02° at best in float32)."""
    a, b = a.double(), b.double()
    return torch.rad2deg(torch.atan2(torch.linalg.cross(a, b).norm(dim=1), torch.sum(a * b, dim=1)))


def _fit(problem: Problem, seed: int = 0) -> tuple[NeuralField, FitModel]:
    torch.manual_seed(seed)
    model = FitModel(GGX(), indirect=True).to(problem.device)
    field = NeuralField(problem.geometry.coords, model.raw_init("pixel"), model.raw_init("smooth"), width=32,
                        material_width=16).to(problem.device)
    return field, model


def test_a_packed_row_unpacks_to_its_batch(blobs: Problem) -> None:
    epoch = epoch_batches(blobs, Tiling.of(blobs), 200, 8, torch.Generator().manual_seed(1))
    capacity = epoch.needs.grown(1.25)
    assert capacity.covers(epoch.needs) and not epoch.needs.covers(capacity)
    # the needs drawn aside, from the counts alone, are those of the epochs built from the same draws
    tiling, draws = Tiling.of(blobs), torch.Generator().manual_seed(1)
    built = functools.reduce(Capacity.union, [epoch_batches(blobs, tiling, 200, 8, draws).needs for _ in range(3)])
    assert drawn_capacity(blobs, tiling, 200, 8, torch.Generator().manual_seed(1), 3) == built
    assert built.covers(epoch.needs)
    batches = epoch.batches()
    assert (epoch.needs.own, epoch.needs.outside, epoch.needs.samples, epoch.needs.pairs, epoch.needs.tv) == (
        max(b.frame_pixels for b in batches), max(b.pixels.numel() - b.frame_pixels for b in batches),
        max(b.samples.numel() for b in batches), max(b.events.numel() for b in batches), max(len(b.tv_pairs) for b in batches))
    packed = epoch.packed(capacity)
    assert packed.shape == (len(epoch), capacity.width) and len(epoch) > 5
    k, co = blobs.frames.count, capacity.own
    unpack = Unpacker(capacity, torch.float32, torch.device("cpu"))
    for row, batch in zip(packed, epoch.batches()):
        padded = unpack(row)
        n, pad = batch.frame_pixels, padded.padding
        outside = batch.pixels.numel() - n
        assert padded.frame_pixels == co and float(pad.pixel.count) == n + outside and float(pad.frame.count) == k * n
        np.testing.assert_array_equal(padded.pixels[:n], batch.pixels[:n])
        np.testing.assert_array_equal(padded.pixels[co:co + outside], batch.pixels[n:])
        assert pad.pixel.mask.sum() == n + outside and pad.pixel.mask[:n].all() and pad.pixel.mask[co:co + outside].all()
        rows = padded.frame_rows.view(k, co)
        np.testing.assert_array_equal(rows[:, :n].reshape(-1), batch.frame_rows)
        assert (pad.frame.mask.view(k, co)[:, :n] == 1).all() and (pad.frame.mask.view(k, co)[:, n:] == 0).all()
        s = batch.samples.numel()
        assert float(pad.sample.count) == s and pad.sample.mask[:s].all() and not pad.sample.mask[s:].any()
        np.testing.assert_array_equal(padded.samples[:s], batch.samples)
        np.testing.assert_array_equal(padded.sample_pixel[:s], batch.sample_pixel)
        frame = batch.sample_group // n
        np.testing.assert_array_equal(padded.sample_group[:s], frame * co + batch.sample_pixel)
        e = batch.events.numel()
        assert float(pad.event.count) == e
        np.testing.assert_array_equal(padded.events[:e], batch.events)
        # each tap reads the same pixel through the padded layout
        np.testing.assert_array_equal(padded.pixels[padded.event_taps[:e]], batch.pixels[batch.event_taps])
        q = batch.tv_pairs.shape[0]
        assert float(pad.tv.count) == q
        np.testing.assert_array_equal(padded.tv_pairs[:q], batch.tv_pairs)
        # padding points at row 0 of whatever it indexes
        assert (padded.samples[s:] == 0).all() and (padded.events[e:] == 0).all() and (padded.pixels[n:co] == 0).all()


@pytest.mark.parametrize("device", ["meta", pytest.param("cuda", marks=pytest.mark.cuda)])
def test_an_epoch_is_packed_on_a_device_with_one_copy_from_the_host(blobs: Problem, device: str) -> None:
    """On a GPU a copy from the host's pageable memory waits for the steps queued before it: the
    batches' counts go over at once (the meta device stands a GPU in on the CPU: it dispatches the same
    copies and computes nothing)."""
    epoch = epoch_batches(blobs, Tiling.of(blobs), 200, 8, torch.Generator().manual_seed(1))
    there = dataclasses.replace(epoch, fields={name: values.to(device) for name, values in epoch.fields.items()})
    capacity = epoch.needs.grown(1.25)
    from_host = FromHost(there.fields["pixels"].device)
    with from_host:
        packed = there.packed(capacity)
    assert from_host.seen == ["_to_copy"] and packed.shape == (len(epoch), capacity.width) and len(epoch) > 5
    if device == "cuda":
        torch.testing.assert_close(packed.cpu(), epoch.packed(capacity), rtol=0, atol=0)


def test_capacities_grow_to_the_next_power_of_two_or_three_times_one_and_an_empty_field_stays_empty() -> None:
    grown = Capacity(own=512, outside=70, samples=39000, pairs=0, tv=890, frames=3, fan=4).grown(1.25)
    assert (grown.own, grown.outside, grown.samples, grown.pairs, grown.tv) == (768, 96, 49152, 0, 1536)
    assert grown.width == 5 + 768 + 96 + 3 * 768 + 3 * 49152 + 0 + 2 * 1536
    ladder = [Capacity(n, 0, 0, 0, 0, 1, 1).grown(1.0).own for n in range(1, 50)]
    assert sorted(set(ladder)) == [1, 2, 3, 4, 6, 8, 12, 16, 24, 32, 48, 64]
    assert all(c >= n for n, c in zip(range(1, 50), ladder))


def test_a_padded_step_has_its_batchs_losses_and_gradients(blobs: Problem) -> None:
    field, model = _fit(blobs)
    epoch = epoch_batches(blobs, Tiling.of(blobs), 200, 8, torch.Generator().manual_seed(2))
    capacity = epoch.needs.grown(1.25)
    packed = epoch.packed(capacity)
    share = torch.tensor(0.7)
    unpack = Unpacker(capacity, blobs.dtype, blobs.device)
    for row, batch in list(zip(packed, epoch.batches()))[:4]:
        results = []
        for which, tv_share in ((batch, 0.7), (unpack(row), share)):
            field.zero_grad()
            loss, parts = losses(blobs, field, model, STAGE, which, tv_share)
            loss.backward()
            results.append((loss.detach(), parts, [p.grad.clone() for p in field.parameters()]))
        (loss_a, parts_a, grads_a), (loss_b, parts_b, grads_b) = results
        assert set(parts_a) == set(parts_b) == {"frame", "event", "tv", "indirect"}
        # the plain batch's event term is the compiled float32 pass, the padded one torch's
        torch.testing.assert_close(loss_b, loss_a, rtol=1e-5, atol=0)
        for name in parts_a:
            torch.testing.assert_close(parts_b[name], parts_a[name], rtol=1e-5, atol=1e-9)
        for a, b in zip(grads_a, grads_b):
            torch.testing.assert_close(b, a, rtol=1e-3, atol=1e-6 * float(a.abs().max()))


def test_a_stage_of_padded_steps_trains_as_the_plain_one(blobs: Problem, monkeypatch: pytest.MonkeyPatch) -> None:
    """``train`` through ``GraphedSteps`` (eager on the CPU, ``graphed.wanted`` told so) against the
    plain loop: the same losses, steps and normals to float rounding, with the pairs' targets replaced
    between two epochs (as the thresholds' refit does), which the steps' own copies take up."""
    pixels = int(blobs.events.pixel.max()) + 1
    gains = np.random.default_rng(0).uniform(0.8, 1.2, (2, pixels))

    def refit(epoch: int) -> None:
        if epoch == 1:
            blobs.events.apply_thresholds(gains[0], gains[1])

    runs = []
    try:
        for padded in (False, True):
            monkeypatch.setattr(graphed, "wanted", lambda problem, compiled, mini_batches, padded=padded: padded)
            blobs.events.apply_thresholds(np.ones(pixels), np.ones(pixels))
            field, model = _fit(blobs)
            history = train(blobs, field, model, STAGE, no_progress, before_epoch=refit)
            with torch.no_grad():
                runs.append((history, field()[0]))
    finally:
        blobs.events.apply_thresholds(np.ones(pixels), np.ones(pixels))
    (plain, normal_a), (padded_run, normal_b) = runs
    assert [h["steps"] for h in plain] == [h["steps"] for h in padded_run] and plain[0]["steps"] > 5
    assert set(plain[0]) == set(padded_run[0]) and "tv" in plain[0]
    for a, b in zip(plain, padded_run):
        for name in a:
            assert b[name] == pytest.approx(a[name], rel=1e-4), name
    assert float(_angle_deg(normal_a, normal_b).max()) < 1e-4  # measured 6.5e-7°


def test_full_batch_steps_train_as_the_plain_ones(blobs_48: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The ``fast`` preset's full-batch steps through ``GraphedSteps`` (eager on the CPU): the event
    pairs each epoch draws read from the static row, the same losses and normals as the plain loop."""
    problem = _problem(blobs_48, frame_samples=8)
    config = dataclasses.replace(STAGE, epochs=6, lr=5e-3, material_lr=5e-2, event_weight=8.0, tv_weight=0.05, tv_fraction=0.3,
                                 event_batch=problem.events.usable.numel() // 2, batch_pixels=0)
    runs = []
    for stepped in (False, True):
        monkeypatch.setattr(graphed, "wanted", lambda problem, compiled, mini_batches, stepped=stepped: stepped)
        torch.manual_seed(0)
        model = FitModel(GGX(), indirect=True)
        field = build_field(PRESETS["fast"], problem, model)
        history = train(problem, field, model, config, no_progress)
        with torch.no_grad():
            runs.append((history, field()[0]))
    (plain, normal_a), (stepped_run, normal_b) = runs
    assert [h["steps"] for h in stepped_run] == [1.0, 1.0] and set(plain[0]) == set(stepped_run[0]) and "tv" in plain[0]
    for a, b in zip(plain, stepped_run):
        for name in a:
            assert b[name] == pytest.approx(a[name], rel=1e-5), name
    assert float(_angle_deg(normal_a, normal_b).max()) < 1e-4


def test_full_batch_graphs_are_wanted_on_cuda_up_to_a_size(blobs: Problem) -> None:
    cuda = SimpleNamespace(device=torch.device("cuda"), geometry=blobs.geometry)
    assert graphed.wanted(cuda, False, False) and graphed.wanted(cuda, False, True)
    assert not graphed.wanted(blobs, False, False) and not graphed.wanted(blobs, False, True) and graphed.wanted(blobs, True, True)
    large = SimpleNamespace(device=torch.device("cuda"), geometry=SimpleNamespace(pixels=np.arange(graphed.FULL_BATCH_PIXELS + 1)))
    assert not graphed.wanted(large, False, False) and graphed.wanted(large, False, True)


def test_compiled_steps_train_as_the_plain_ones(blobs: Problem, monkeypatch: pytest.MonkeyPatch) -> None:
    """``compiled`` steps trace the whole step in one graph (``fullgraph``: no break, so inductor may
    fuse all of it; traced here with aot_eager, which runs the traced graph as torch would) and train
    as the plain loop does."""
    monkeypatch.setattr(graphed, "COMPILE_BACKEND", "aot_eager")
    torch._dynamo.reset()
    runs = []
    for compiled in (False, True):
        field, model = _fit(blobs)
        history = train(blobs, field, model, dataclasses.replace(STAGE, compiled=compiled), no_progress)
        with torch.no_grad():
            runs.append((history, field()[0]))
    # one graph with the TV term's share a tensor, one without the term (its share 0 from the third epoch)
    assert torch._dynamo.utils.counters["stats"]["unique_graphs"] == 2
    (plain, normal_a), (compiled_run, normal_b) = runs
    for a, b in zip(plain, compiled_run):
        assert b["loss"] == pytest.approx(a["loss"], rel=1e-4)
    assert float(_angle_deg(normal_a, normal_b).max()) < 1e-4


@pytest.mark.parametrize(("device", "stepped"), [("cpu", False), ("cpu", True), pytest.param("cuda", True, marks=pytest.mark.cuda)])
def test_a_stage_set_aside_and_taken_up_again_trains_as_one_never_stopped(blobs_48: Path, monkeypatch: pytest.MonkeyPatch,
                                                                         device: str, stepped: bool) -> None:
    """A ``Training`` stopped after two epochs, another trained on the same field in between (with its own
    draws, Adam and, on a GPU, graphs) and the parameters put back, then run to its end: the normals and
    history of a stage never stopped (bit for bit on the CPU; on a GPU, whose scatter-adds are not
    deterministic, to float rounding), plain and padded steps."""
    problem = _problem(blobs_48, device)
    if device == "cpu":
        monkeypatch.setattr(graphed, "wanted", lambda problem, compiled, mini_batches: stepped)
    config = dataclasses.replace(STAGE, epochs=5)
    # deterministic scatter-adds on the CPU, as the solver runs (``solver.deterministic``)
    with deterministic(torch.device(device)):
        field, model = _fit(problem)
        history = train(problem, field, model, config, no_progress)
        with torch.no_grad():
            expected = field()[0].cpu()
        field, model = _fit(problem)
        training = Training(problem, field, model, config, no_progress)
        training.run(2)
        assert training.epoch == 2 and len(training.history) == 1
        kept = (copy.deepcopy(field.state_dict()), [p.detach().clone() for p in model.parameters()])
        other = Training(problem, field, model, dataclasses.replace(config, seed=3, lr=1e-2), no_progress)
        other.run()
        other.close()
        with torch.no_grad():
            assert float(_angle_deg(field()[0].cpu(), expected).max()) > 0.1  # the other fit moved the surface
        field.load_state_dict(kept[0])
        with torch.no_grad():
            for parameter, value in zip(model.parameters(), kept[1]):
                parameter.copy_(value)
        training.run()
        training.close()
        assert training.epoch == config.epochs
        with torch.no_grad():
            normal = field()[0].cpu()
    assert [h["epoch"] for h in training.history] == [h["epoch"] for h in history]
    if device == "cpu":
        assert torch.equal(normal, expected) and training.history == history
    else:
        assert float(_angle_deg(normal, expected).max()) < 1e-3
        for a, b in zip(history, training.history):
            assert b["loss"] == pytest.approx(a["loss"], rel=1e-4)


def test_a_capture_that_fails_is_tried_again_then_left_eager(blobs: Problem, monkeypatch: pytest.MonkeyPatch) -> None:
    """A failed capture (on a GPU: a garbage collection that destroyed another graph during it, say) is
    tried again at the next step, and after ``CAPTURE_TRIES`` the steps stay eager with one warning;
    the collector is off while a step is captured (CUDA's capture stood in for on the CPU)."""
    fails: list[bool] = []
    collecting: list[bool] = []
    replays: list[int] = []

    class Graph:
        def replay(self) -> None:
            replays.append(1)

    @contextlib.contextmanager
    def capture(graph: Graph):  # type: ignore[no-untyped-def]
        collecting.append(gc.isenabled())
        yield
        if fails.pop(0) if fails else True:
            raise RuntimeError("CUDA error: operation failed due to a previous error during capture")

    monkeypatch.setattr(torch.cuda, "CUDAGraph", Graph)
    monkeypatch.setattr(torch.cuda, "graph", capture)
    monkeypatch.setattr(graphed.GraphedSteps, "_eager", lambda self, tv_on: self._step(tv_on))
    epoch = epoch_batches(blobs, Tiling.of(blobs), 200, 8, torch.Generator().manual_seed(4))
    assert len(epoch) > 5
    for plan in ([True, True, False], [True] * 10):
        fails[:], collecting[:], replays[:] = plan, [], []
        field, model = _fit(blobs)
        optimizer = torch.optim.Adam([*field.parameters(), *model.parameters()], lr=1e-3)
        steps = graphed.GraphedSteps(blobs, Tiling.of(blobs), field, model, STAGE, optimizer, use_graphs=True)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            steps.epoch(epoch, 0.5)
        assert collecting == [False] * graphed.CAPTURE_TRIES and gc.isenabled()
        messages = [str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)]
        if plan[2]:
            assert not steps.use_graphs and replays == [] and len(messages) == 1 and "in 3 tries" in messages[0]
        else:
            assert steps.use_graphs and len(replays) == len(epoch) - 3 and messages == []


@pytest.mark.cuda
@pytest.mark.parametrize("batches", ["mini", "full"])
def test_cuda_graphs_replay_the_steps_they_capture(blobs_48: Path, monkeypatch: pytest.MonkeyPatch, batches: str) -> None:
    """On a GPU: a stage replayed as CUDA graphs (captured, no warning) against the same steps run
    eagerly there, of mini-batches (the paper's network) and of full batches (the pyramid)."""
    problem = _problem(blobs_48, "cuda", frame_samples=0 if batches == "mini" else 8)
    config = STAGE if batches == "mini" else dataclasses.replace(
        STAGE, epochs=6, lr=5e-3, material_lr=5e-2, event_weight=8.0, event_batch=problem.events.usable.numel() // 2, batch_pixels=0)
    capture = graphed.GraphedSteps._capture
    captures: list[bool] = []
    runs = []
    for replay in (False, True):
        if batches == "mini":
            field, model = _fit(problem)
        else:
            torch.manual_seed(0)
            model = FitModel(GGX(), indirect=True).to(problem.device)
            field = build_field(PRESETS["fast"], problem, model)
        if replay:
            monkeypatch.setattr(graphed.GraphedSteps, "_capture", lambda self, tv_on: captures.append(tv_on) or capture(self, tv_on))
        else:
            monkeypatch.setattr(graphed.GraphedSteps, "_capture", lambda self, tv_on: None)
        with warnings.catch_warnings():
            warnings.simplefilter("error", RuntimeWarning)
            history = train(problem, field, model, config, no_progress)
        monkeypatch.undo()
        with torch.no_grad():
            runs.append((history, field()[0].cpu()))
    assert True in captures and False in captures  # with the TV term, then without
    (eager, normal_a), (replayed, normal_b) = runs
    for a, b in zip(eager, replayed):
        assert b["loss"] == pytest.approx(a["loss"], rel=1e-3)
    assert float(_angle_deg(normal_a, normal_b).mean()) < 0.05


def _as_on_a_gpu(monkeypatch: pytest.MonkeyPatch) -> None:
    """The losses through torch as on a GPU, where the CPU takes its compiled passes (``frame_kernel``,
    ``event_kernel``, ``gather``), which read numpy arrays."""
    monkeypatch.setattr(losses_module, "supports", lambda model, normal: False)
    monkeypatch.setattr(gather._GatherSum, "apply", staticmethod(gather.gather_sum_torch))


def test_a_padded_step_reads_nothing_back_from_the_device(blobs: Problem, monkeypatch: pytest.MonkeyPatch) -> None:
    """What a CUDA graph captures — unpacking the row, the losses and their gradient — holds no
    operation that waits for the device or copies from the host (checked through torch on the CPU,
    which runs the same ops)."""
    field, model = _fit(blobs)
    epoch = epoch_batches(blobs, Tiling.of(blobs), 200, 8, torch.Generator().manual_seed(4))
    capacity = epoch.needs.grown(1.25)
    row = epoch.packed(capacity)[0]
    unpack = Unpacker(capacity, blobs.dtype, blobs.device)
    share = torch.tensor(0.5)
    _as_on_a_gpu(monkeypatch)
    reads = ReadsBack()
    with reads:
        loss, _ = losses(blobs, field, model, STAGE, unpack(row), share)
        loss.backward()
    assert reads.seen == []
    # the check sees what it looks for: a boolean mask reads its count back, a literal is host data
    with reads:
        blobs.frames.sample_weight[blobs.frames.sample_weight[:, 0] > 0]
        blobs.frames.sample_weight.new_tensor([1.0, -1.0])
    assert reads.seen == ["index", "lift_fresh"]


def test_a_full_batch_step_reads_nothing_back_from_the_device(blobs_48: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The ``fast`` preset's full-batch step as a CUDA graph captures it (``GraphedSteps._full_losses``:
    the pairs drawn, the losses in one frame chunk, their gradient) holds no operation that waits for the
    device or copies from the host."""
    problem = _problem(blobs_48, frame_samples=8)
    torch.manual_seed(0)
    model = FitModel(GGX(), indirect=True)
    field = build_field(PRESETS["fast"], problem, model)
    config = dataclasses.replace(STAGE, event_weight=8.0, tv_weight=0.05, batch_pixels=0)
    events, share = problem.events.usable[::2], torch.tensor(0.5)
    _as_on_a_gpu(monkeypatch)
    reads = ReadsBack()
    with reads:
        batch = full_batch(problem, events, problem.geometry.pixels.size)
        loss, parts = losses(problem, field, model, config, batch, share)
        loss.backward()
    assert reads.seen == [] and {"frame", "event", "tv"} <= set(parts)
