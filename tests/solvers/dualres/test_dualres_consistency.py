"""The event pixels' consistency gate (``pstoolkit_dualres.consistency``) and the indirect-light map."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

import psfmt
from pstoolkit.optics.brdf import GGX
from pstoolkit_dualres.consistency import MIN_PAIRS, event_gate, pair_residuals
from pstoolkit_dualres.fields import PyramidField
from pstoolkit_dualres.preprocess import PreprocessOptions, preprocess
from pstoolkit_dualres.problem import Problem, build_problem
from pstoolkit_dualres.reflectance import FitModel


@pytest.fixture(scope="module")
def fitted(sphere_48: Path) -> tuple[Problem, PyramidField, FitModel, int]:
    """The 48 px sphere's problem with a field at its true normals and the closed form's albedo."""
    capture = psfmt.read(sphere_48)
    pre = preprocess(capture, PreprocessOptions())
    problem = build_problem(pre, capture.calibration.view_direction, device="cpu")
    geometry = problem.geometry
    model = FitModel(GGX())
    truth = torch.as_tensor(np.asarray(capture.ground_truth.normal).reshape(-1, 3)[geometry.pixels], dtype=torch.float32)
    field = PyramidField((geometry.height, geometry.width), geometry.pixels, truth, model.pixel_raw_from(geometry.init_albedo),
                         geometry.event_shape, geometry.grid_taps, model.raw_init("smooth"))
    return problem, field, model, pre.event_height * pre.event_width


def test_the_residuals_are_those_of_the_event_term(fitted: tuple[Problem, PyramidField, FitModel, int]) -> None:
    """``pair_residuals`` squared and weighted sum to the plain event term of the same pairs."""
    from pstoolkit_dualres.losses import pair_event_loss

    problem, field, model, _ = fitted
    pairs = problem.events.usable[:500]
    residual = pair_residuals(problem, field, model, pairs)
    with torch.no_grad():
        normal, pixel_raw, smooth_raw = field()
        term = pair_event_loss(model, normal, model.maps(pixel_raw, smooth_raw), problem.events.taps[pairs], problem.events, pairs,
                               problem.geometry.view)
    weight = problem.events.weight[pairs].double().numpy()
    assert float(term) == pytest.approx(float(np.sum(weight * residual**2) / pairs.numel()), rel=1e-4)


def test_a_pixel_whose_events_the_fit_cannot_explain_is_gated(fitted: tuple[Problem, PyramidField, FitModel, int]) -> None:
    """On a sphere fitted at its true normals every event pixel keeps its weight (κ = 3, floor half of
    C = 0.15; without the floor the rim, ten times the typical residual of a near-perfect fit, would
    be gated); shifting the targets of one pixel's pairs by 0.5 log units (light the model does not
    have) gates that pixel alone, weighs its pairs by (bound/scale)² and restarts it; the pairs'
    weights follow."""
    problem, field, model, n_event = fitted
    events = problem.events
    clean = event_gate(problem, field, model, n_event, 3.0, 0.075)
    measured = ~np.isnan(clean.scale)
    assert measured.sum() > 100 and np.all(clean.weight[measured] == 1.0)
    assert np.any(event_gate(problem, field, model, n_event, 3.0, 0.0).weight < 1.0)
    pixel = events.pixel
    usable = events.usable.numpy()
    counts = np.bincount(pixel[usable], minlength=n_event)
    victim = int(np.argmax(counts))
    assert counts[victim] >= MIN_PAIRS
    saved = events.target.clone()
    try:
        events.target[torch.as_tensor(pixel == victim)] += 0.5
        gate = event_gate(problem, field, model, n_event, 3.0, 0.075)
    finally:
        events.target = saved
    assert np.flatnonzero(gate.weight < 1.0).tolist() == [victim]
    assert gate.restart[victim] and gate.restart.sum() == 1
    assert gate.weight[victim] == pytest.approx((max(3.0 * gate.typical, 0.075) / gate.scale[victim]) ** 2)
    events.apply_gate(gate.weight)
    try:
        on_victim = torch.as_tensor(pixel == victim)
        expected = events.source["weight"][pixel == victim] * gate.weight[victim]
        torch.testing.assert_close(events.weight[on_victim], torch.as_tensor(expected, dtype=torch.float32))
        torch.testing.assert_close(events.weight[~on_victim], torch.as_tensor(events.source["weight"][pixel != victim], dtype=torch.float32))
    finally:
        events.apply_gate(np.ones(n_event))


def test_indirect_light_is_a_smooth_map_the_brdf_never_sees() -> None:
    """``indirect`` adds one smooth map, starting near 0; ``shade`` renders as without it, and the
    light it gives is ρ_d·b."""
    plain, with_b = FitModel(GGX()), FitModel(GGX(), indirect=True)
    assert with_b.smooth_channels == plain.smooth_channels + 1
    raw_pixel = torch.zeros(4, with_b.pixel_channels)
    raw_smooth = with_b.raw_init("smooth").expand(4, -1)
    maps = with_b.maps(raw_pixel, raw_smooth)
    assert torch.allclose(maps["indirect"], torch.full((4, 1), 1e-3))
    n = torch.tensor([[0.0, 0.0, 1.0]]).expand(4, 3)
    l = torch.nn.functional.normalize(torch.tensor([[0.3, 0.2, 1.0]]), dim=1).expand(4, 3)
    v = torch.tensor([0.0, 0.0, 1.0])
    plain_maps = {k: value for k, value in maps.items() if k != "indirect"}
    torch.testing.assert_close(with_b.shade(n, l, v, maps), plain.shade(n, l, v, plain_maps))
    torch.testing.assert_close(with_b.indirect_light(maps), maps["albedo"] * 1e-3)
    assert plain.indirect_light(plain_maps) is None
