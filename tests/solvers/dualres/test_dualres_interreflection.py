"""One bounce of inter-reflection from the fitted surface (``pstoolkit_dualres.interreflection`` and
``bounce``, option ``interreflection``), on the host and on a device (``bounce_device``)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from helpers.device_path import masked_problems, on_the_host

import psfmt
from pstoolkit.errors import UserError
from pstoolkit.optics.brdf import Lambertian
from pstoolkit.shadows.score import true_shadows
from pstoolkit.sim.config import SimulationConfig
from pstoolkit.sim.simulator import simulate
from pstoolkit.solve.api import solve_capture
from pstoolkit.surface import integrate_normals
from pstoolkit_dualres import solver
from pstoolkit_dualres.bounce import MIN_NZ, one_bounce
from pstoolkit_dualres.interreflection import remove_bounce
from pstoolkit_dualres.preprocess import PreprocessOptions, preprocess
from pstoolkit_dualres.problem import build_problem
from pstoolkit_dualres.reflectance import FitModel


def _groove(size: int, depth_per_px: float) -> tuple[np.ndarray, np.ndarray]:
    """A V-groove along y: height −depth·(size/2 − |x − centre|) in pixels, and its unit normals."""
    x = np.arange(size) - (size - 1) / 2.0
    slope = np.where(x < 0, -depth_per_px, depth_per_px)
    height = np.tile(depth_per_px * np.abs(x) - depth_per_px * size / 2.0, (size, 1))
    normal = np.zeros((size, size, 3))
    normal[..., 0] = -np.tile(slope, (size, 1))
    normal[..., 2] = 1.0
    return height, normal / np.linalg.norm(normal, axis=-1, keepdims=True)


def _visible(height: np.ndarray, a: tuple[int, int], b: tuple[int, int]) -> bool:
    """The height field's visibility between cells ``a`` and ``b`` (row, column): no cell the segment
    passes over (sampled once per cell of its longer side) is more than half a cell above it."""
    steps = max(abs(b[0] - a[0]), abs(b[1] - a[1]))
    for s in range(1, steps):
        f = s / steps
        v, u = int(round(a[0] + f * (b[0] - a[0]))), int(round(a[1] + f * (b[1] - a[1])))
        if height[v, u] > height[a] + f * (height[b] - height[a]) + 0.5:
            return False
    return True


def _brute_force(normal: np.ndarray, albedo: np.ndarray, height: np.ndarray, direct: np.ndarray, radius: int) -> np.ndarray:
    """The module docstring's sum, written out pair by pair."""
    h, w = height.shape
    out = np.zeros((direct.shape[-1], h * w, 3))
    cells = [(v, u) for v in range(h) for u in range(w)]
    for i, (v, u) in enumerate(cells):
        for j, (vy, uy) in enumerate(cells):
            if i == j or (vy - v) ** 2 + (uy - u) ** 2 > radius * radius or not _visible(height, (v, u), (vy, uy)):
                continue
            offset = np.array([uy - u, -(vy - v), height[vy, uy] - height[v, u]], dtype=np.float64)
            r2 = float(offset @ offset)
            cos_x = float(offset @ normal[v, u]) / math.sqrt(r2)
            cos_y = -float(offset @ normal[vy, uy]) / math.sqrt(r2)
            if cos_x <= 0 or cos_y <= 0:
                continue
            k = cos_x * cos_y / (math.pi * r2) / max(normal[vy, uy, 2], MIN_NZ)
            out[:, i] += k * direct[vy, uy][:, None] * albedo[vy, uy][None, :]
    return out


def test_the_bounce_is_the_sum_it_states_on_a_groove_and_nothing_on_a_plane() -> None:
    size = 12
    height, normal = _groove(size, 2.0)  # walls steeper than the light: one wall dark at each phase
    mask = np.ones((size, size), dtype=bool)
    albedo = np.random.default_rng(3).uniform(0.2, 0.9, (size, size, 3))
    phase = np.array([0.25, 0.75]) * 1000.0
    directions = np.array([[0.6, 0.0, 0.8], [-0.6, 0.0, 0.8]])
    lit = np.ones((2, size * size), dtype=bool)
    bounce = one_bounce(normal, albedo, height, mask, lit, directions, phase, 1000.0)
    direct = np.clip(normal @ directions.T, 0.0, None)
    expected = _brute_force(normal, albedo, height, direct, radius=32)
    np.testing.assert_allclose(bounce.value, expected, rtol=1e-5, atol=1e-9)
    # light from +x lights the left wall (normals towards +x) only: its light reaches the right wall
    left, right = slice(0, size // 2), slice(size // 2, size)
    at_plus = bounce.value[0].reshape(size, size, 3)
    assert at_plus[:, right].min() > 0.0
    assert np.all(at_plus[:, left] == 0.0)
    # halfway between the two phases, cyclically, the mean of both, at one pixel or at all
    halfway = 0.5 * bounce.value[0] + 0.5 * bounce.value[1]
    np.testing.assert_allclose(bounce.everywhere(500.0), halfway, rtol=1e-6)
    np.testing.assert_allclose(bounce.everywhere(0.0), halfway, rtol=1e-6)
    np.testing.assert_allclose(bounce.at(np.array([500.0, 250.0]), np.array([7, 7])), [halfway[7], bounce.value[0, 7]], rtol=1e-6)
    flat = one_bounce(np.dstack([np.zeros((size, size, 2)), np.ones((size, size))]), albedo, np.zeros((size, size)), mask, lit,
                      directions, phase, 1000.0)
    assert np.all(flat.value == 0.0)


def test_a_wall_between_two_patches_blocks_their_exchange() -> None:
    """Two walls facing each other across a ridge taller than both see nothing of each other."""
    size = 12
    height, normal = _groove(size, 0.8)
    open_bounce = one_bounce(normal, np.ones((size, size, 3)), height, np.ones((size, size), bool), np.ones((1, size * size), bool),
                             np.array([[0.6, 0.0, 0.8]]), np.array([250.0]), 1000.0).value
    walled = height.copy()
    walled[:, size // 2 - 1 : size // 2 + 1] = 50.0
    blocked = one_bounce(normal, np.ones((size, size, 3)), walled, np.ones((size, size), bool), np.ones((1, size * size), bool),
                         np.array([[0.6, 0.0, 0.8]]), np.array([250.0]), 1000.0).value
    right = (np.arange(size * size) % size) >= size // 2 + 1
    assert open_bounce[0, right].sum() > 0.0
    assert np.all(blocked[0, right] == 0.0)


def test_the_terms_compose_their_thresholds_gate_and_bounce(sphere_48: Path) -> None:
    """Targets are the thresholds' steps plus the bounce's shift, weights the built ones times the gate
    times the bounce's keep, whatever the order; a zero bounce gives the terms back; the frames as
    built minus the offset."""
    capture = psfmt.read(sphere_48)
    pre = preprocess(capture, PreprocessOptions())
    problem = build_problem(pre, capture.calibration.view_direction, device="cpu")
    events, frames = problem.events, problem.frames
    src = events.source
    built_target, built_weight = events.target.clone(), events.weight.clone()
    n_pixels = pre.event_height * pre.event_width
    rng = np.random.default_rng(5)
    gain_pos, gain_neg, gate = rng.uniform(0.9, 1.1, n_pixels), rng.uniform(0.9, 1.1, n_pixels), rng.uniform(0.5, 1.0, n_pixels)
    count = events.target.shape[0]
    shift, keep = rng.normal(0.0, 0.05, count), rng.uniform(size=count) > 0.2
    steps = src["rise"] * gain_pos[src["pixel"]] - src["fall"] * gain_neg[src["pixel"]]
    expected_target = steps + shift
    expected_weight = src["weight"] * gate[src["pixel"]] * keep
    for order in ((0, 1, 2), (2, 0, 1), (1, 2, 0)):
        events.apply_bounce(np.zeros(count), np.ones(count, bool), np.zeros(count), np.zeros(count))
        events.apply_gate(np.ones(n_pixels))
        events.apply_thresholds(np.ones(n_pixels), np.ones(n_pixels))
        np.testing.assert_allclose(events.target.numpy(), built_target.numpy(), atol=1e-6)
        np.testing.assert_array_equal(events.weight.numpy(), built_weight.numpy())
        steps_in = (lambda: events.apply_thresholds(gain_pos, gain_neg), lambda: events.apply_gate(gate),
                    lambda: events.apply_bounce(shift, keep, np.ones(count), np.ones(count)))
        for index in order:
            steps_in[index]()
        np.testing.assert_allclose(events.target.numpy(), expected_target, rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(events.weight.numpy(), expected_weight, rtol=1e-6)
    measured = frames.measured.clone()
    offset = rng.uniform(0.0, 0.01, measured.shape)
    built = frames.apply_bounce(offset)
    np.testing.assert_array_equal(built, measured.numpy())
    np.testing.assert_allclose(frames.measured.numpy(), measured.numpy() - offset, rtol=1e-6, atol=1e-7)
    frames.apply_bounce(np.zeros_like(offset))
    np.testing.assert_array_equal(frames.measured.numpy(), measured.numpy())


@pytest.fixture(scope="module")
def hollows_48(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The simulator's hollows (direct light only) at 48 px: a concavity whose bounce the model predicts."""
    path = tmp_path_factory.mktemp("hollows_48") / "hollows.h5"
    simulate(SimulationConfig(scene="hollows", size=48, seed=0), path)
    return path


def test_a_bounce_the_measurements_do_not_have_is_tried_and_left_out(hollows_48: Path) -> None:
    """The simulator renders no inter-reflection: with the default (auto) the fit with the bounce explains
    the measurements worse, so the fit without is kept, exactly as with the bounce off; a bounce forced
    on changes the normals and records what it took out. The choice at the preset's epochs: after 30 the
    fit with the bounce (and its mask) leaves 9 % more unexplained, after 150 37 %."""
    auto = solve_capture(hollows_48, "dualres")
    off = solve_capture(hollows_48, "dualres", interreflection="off")
    forced = solve_capture(hollows_48, "dualres", epochs=30, interreflection="on")
    stage = next(stage for stage in auto.diagnostics["stages"] if "interreflection" in stage)
    chosen = stage["interreflection"]
    assert chosen["kept"] is False and chosen["bounce_frame_share"] > 0.002
    # the fit with the bounce took the mask of a surface inter-reflection flattened: more shadow
    assert chosen["cast_shadow_share_with"] > stage["cast_shadow_share"]
    assert chosen["unexplained_with"] > 1.1 * chosen["unexplained_without"]
    np.testing.assert_array_equal(auto.normal, off.normal)
    assert not any("interreflection" in stage or "bounce_frame_share" in stage for stage in off.diagnostics["stages"])
    record = next(stage for stage in forced.diagnostics["stages"] if "bounce_frame_share" in stage)
    assert 0.002 < record["bounce_frame_share"] < 0.5 and 0.0 <= record["bounce_pairs_dropped"] < 0.5
    short = solve_capture(hollows_48, "dualres", epochs=30, interreflection="off")
    assert np.degrees(np.arccos(np.clip(np.sum(forced.normal * short.normal, axis=-1), -1, 1)))[off.mask].max() > 1.0
    # a higher reflectance takes out more
    brighter = solve_capture(hollows_48, "dualres", epochs=30, interreflection="on", bounce_reflectance=1.2)
    more = next(stage for stage in brighter.diagnostics["stages"] if "bounce_frame_share" in stage)
    assert more["bounce_frame_share"] > 1.5 * record["bounce_frame_share"]


def test_the_fit_chosen_early_goes_on_as_if_the_other_had_never_run(hollows_48: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``bounce_early``: the two fits take turns to each of ``BOUNCE_CHECKS`` and are compared there; once
    the comparison clears its margin the one kept goes on alone, to the normals it ends with when both go
    to the end (bit for bit; the other fit ran in between). At 30 epochs (the first re-detection at 12) the
    bounce is kept when the fits are compared at 21 or 30 and left out at 16, then exactly as with the
    bounce off; a check whose margin is not cleared goes on to the next. The checks are recorded, and
    the progress bar rises to the end."""
    def choice(solution: object) -> dict[str, Any]:
        return next(stage for stage in solution.diagnostics["stages"] if "interreflection" in stage)["interreflection"]

    reported: list[float] = []
    late = solve_capture(hollows_48, "dualres", epochs=30, bounce_early=False)
    monkeypatch.setattr(solver, "BOUNCE_CHECKS", ((0.2, 1.0), (0.5, 0.0)))
    early = solve_capture(hollows_48, "dualres", epochs=30, progress=lambda fraction, message: reported.append(fraction))
    monkeypatch.setattr(solver, "BOUNCE_CHECKS", ((0.2, 0.0),))
    earlier = solve_capture(hollows_48, "dualres", epochs=30)
    off = solve_capture(hollows_48, "dualres", epochs=30, interreflection="off")
    assert (choice(late)["kept"], choice(late)["decided_at_epoch"], len(choice(late)["checks"])) == (True, 30, 1)
    assert (choice(early)["kept"], choice(early)["decided_at_epoch"]) == (True, 21)
    assert [check["epoch"] for check in choice(early)["checks"]] == [16, 21]
    assert choice(early)["unexplained_with"] == choice(early)["checks"][-1]["unexplained_with"]
    assert (choice(earlier)["kept"], choice(earlier)["decided_at_epoch"]) == (False, 16)
    check = choice(earlier)["checks"][0]
    assert check["unexplained_with"] > 1.1 * check["unexplained_without"]
    np.testing.assert_array_equal(early.normal, late.normal)
    np.testing.assert_array_equal(earlier.normal, off.normal)
    assert not np.array_equal(late.normal, off.normal)
    assert reported == sorted(reported) and reported[-1] == pytest.approx(1.0) and sum(f > 0.5 for f in reported) >= 2


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.cuda)])
def test_the_sum_over_the_cells_on_a_device_is_the_compiled_kernels(device: str) -> None:
    """``bounce_device._sum_there`` against ``bounce._bounce`` on rough cells with holes and a wall (pairs
    the wall blocks, pairs beyond the radius, rounding halfway between cells), the radius inside the
    grid and past it."""
    from pstoolkit_dualres.bounce import _bounce
    from pstoolkit_dualres.bounce_device import _sum_there

    rng = np.random.default_rng(5)
    hc, wc, t_count = 17, 22, 4
    height = rng.normal(0.0, 1.5, (hc, wc))
    height[:, 10] = 12.0
    normal = rng.normal(0.0, 0.4, (hc, wc, 3))
    normal[..., 2] = 1.0
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    albedo, direct = rng.uniform(0.1, 0.9, (hc, wc, 3)), rng.uniform(0.0, 1.0, (hc, wc, t_count))
    inside = rng.random((hc, wc)) > 0.15
    v, u = np.mgrid[0:hc, 0:wc].astype(np.float64)
    point = np.stack([u, -v, height], axis=-1)
    for radius in (6, 32):
        expected = np.zeros((hc, wc, t_count, 3))
        _bounce(point, normal, albedo, direct, inside, height, radius, expected)
        there = _sum_there(*(torch.as_tensor(a, device=device) for a in (point, normal, albedo, direct, inside, height)), radius)
        np.testing.assert_allclose(there.cpu().numpy().reshape(hc, wc, t_count, 3), expected, rtol=1e-12, atol=1e-15)
    open_wall = height.copy()
    open_wall[:, 10] = 0.0
    unblocked = np.zeros((hc, wc, t_count, 3))
    _bounce(point, normal, albedo, direct, inside, open_wall, 32, unblocked)
    # the wall blocks some pairs, and the exchange is not empty
    assert expected.max() > 0.0 and not np.allclose(unblocked, expected)


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.cuda)])
def test_the_bounce_taken_out_on_the_device_is_the_hosts(hollows_48: Path, device: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """``remove_bounce`` down the device's path (``bounce_device``) changes the frames and the pairs as the
    host's does, for the shared grid's samples and the importance samples."""
    capture = psfmt.read(hollows_48)
    pre = preprocess(capture, PreprocessOptions())
    gt = capture.ground_truth
    truth = true_shadows(gt.depth, gt.mask, pre.light, pre.t0_us, pre.period_us)
    height = integrate_normals(gt.normal, gt.mask)
    model = FitModel(Lambertian())
    for frame_samples in (8, 0):
        host, there = masked_problems(pre, capture.calibration.view_direction, truth, frame_samples, device, monkeypatch)
        p = host.geometry.pixels.size
        normal = torch.as_tensor(gt.normal.reshape(-1, 3)[host.geometry.pixels], dtype=torch.float32)
        maps = model.maps(torch.full((p, model.pixel_channels), 0.3), torch.zeros(p, model.smooth_channels))
        with on_the_host(monkeypatch):
            expected = remove_bounce(host, model, normal, maps, height, truth, pre.light, pre.t0_us, pre.period_us, 0.8)
        got = remove_bounce(there, model.to(device), normal.to(device), {k: v.to(device) for k, v in maps.items()}, height,
                            truth, pre.light, pre.t0_us, pre.period_us, 0.8)
        assert expected["bounce_frame_share"] > 0.002 and 0.0 < expected["bounce_pairs_dropped"] < 0.5
        assert got == pytest.approx(expected, rel=1e-6)
        # the cells' and the samples' sums are taken in another order: float rounding apart
        np.testing.assert_allclose(there.frames.measured.cpu().numpy(), host.frames.measured.numpy(), rtol=1e-6, atol=1e-7)
        for name in ("bounce_now", "bounce_ref"):
            np.testing.assert_allclose(there.events.source[name], host.events.source[name], rtol=1e-6, atol=1e-9, err_msg=name)
        # the shift is a log ratio of the fit's own float32 rendering of the pairs, which a GPU rounds
        # otherwise (a few ulps: 4.2e-7 at most on an H200)
        np.testing.assert_allclose(there.events.source["bounce_shift"], host.events.source["bounce_shift"], rtol=1e-6,
                                   atol=1e-9 if device == "cpu" else 2e-6)
        assert np.array_equal(there.events.source["bounce_keep"], host.events.source["bounce_keep"])


def test_the_bounce_takes_the_height_the_detector_integrated(hollows_48: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The surface the bounce is fitted with is the one the detector just swept: one integration serves
    both, so a fit that tries the bounce integrates as many surfaces as one without it (the closed
    form's and the first stage's) and the heights the bounce models agree with a fresh solve."""
    import pstoolkit.surface
    import pstoolkit_dualres.interreflection as interreflection

    solved: list[np.ndarray] = []
    modelled: list[np.ndarray] = []
    integrate = pstoolkit.surface.integrate_normals
    bounce = interreflection.one_bounce

    def counted(normal: np.ndarray, mask: np.ndarray) -> np.ndarray:
        solved.append(integrate(normal, mask))
        return solved[-1]

    def seen(normal: np.ndarray, albedo: np.ndarray, height: np.ndarray, mask: np.ndarray, *rest: object) -> object:
        modelled.append(integrate(normal, mask) - height)
        return bounce(normal, albedo, height, mask, *rest)

    monkeypatch.setattr(pstoolkit.surface, "integrate_normals", counted)
    monkeypatch.setattr(interreflection, "one_bounce", seen)
    solve_capture(hollows_48, "dualres", epochs=30, interreflection="off")
    without = len(solved)
    auto = solve_capture(hollows_48, "dualres", epochs=30)
    assert any("interreflection" in stage for stage in auto.diagnostics["stages"])
    assert without == 2 and len(solved) == 2 * without
    assert len(modelled) == 1 and np.abs(modelled[0]).max() < 1e-9


def test_bad_interreflection_options_are_refused(sphere_48: Path) -> None:
    with pytest.raises(UserError, match="'sometimes' is not one of auto, on, off"):
        solve_capture(sphere_48, "dualres", epochs=2, interreflection="sometimes")
    with pytest.raises(UserError, match="below the minimum"):
        solve_capture(sphere_48, "dualres", epochs=2, bounce_reflectance=0.0)
    with pytest.raises(UserError, match="bounce_reflectance=0.8 cannot apply with interreflection=off"):
        solve_capture(sphere_48, "dualres", epochs=2, interreflection="off", bounce_reflectance=0.8)
    with pytest.raises(UserError, match=r"^dualres: option bounce_early=false cannot apply with interreflection=on: it is "
                                        "when auto compares its fits with and without the bounce$"):
        solve_capture(sphere_48, "dualres", epochs=2, interreflection="on", bounce_early=False)
