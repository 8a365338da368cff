"""Shadows the events see by their edges (``pstoolkit.shadows.edge_seen``) and ``fused``'s use of them:
light that fills a cast shadow breaks its dark spans but not its edges."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from helpers.event_rows import event_stream

import psfmt
from pstoolkit.plugin.manager import get_registries
from pstoolkit.shadows import ShadowEvidence, fused, geometry, interval_profile
from pstoolkit.shadows.edge_seen import seen_shadows
from pstoolkit.shadows.edge_tracking import SuperPixels
from pstoolkit.shadows.height_scale import period_keys, within
from pstoolkit.shadows.intervals import grid_times
from pstoolkit.shadows.score import score, true_shadows
from pstoolkit.shadows.surface_sweep import integrated_height, surface_height
from pstoolkit.sim.config import SimulationConfig
from pstoolkit.sim.simulator import simulate
from pstoolkit_dualres.preprocess import PreprocessOptions, preprocess

T = 33_333.0
# Light inside the shadows: one event every FILL_US, polarities alternating, as a bounce that flickers,
# from one refractory period (2 ms) after the shadow's entry to one before its exit.
FILL_US = 1000.0


def test_the_keys_count_each_polarity_across_the_period_ends() -> None:
    rows = [[(500.0, -1), (600.0, -1), (700.0, 1)], [(33_000.0, 1)]]
    profile = interval_profile(event_stream(rows), 2, t0_us=0.0, period_us=T, contrast_pos=0.15, contrast_neg=0.15)
    falling, rising = period_keys(profile)
    assert len(falling) == 3 * 2 and len(rising) == 3 * 2 and np.all(np.diff(falling) > 0)
    # around pixel 0's phase 600 µs: two falls, one rise; pixel 1's rise at 33 000 µs is 433 µs before phase 100
    assert within(falling, np.array([0]), np.array([600.0]), T, 200.0)[0] == 2
    assert within(rising, np.array([0]), np.array([600.0]), T, 200.0)[0] == 1
    assert within(rising, np.array([1]), np.array([100.0]), T, 500.0)[0] == 1


@pytest.fixture(scope="module")
def lit_shadows(tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    """48 px GGX blobs (no pixel in shadow for over a quarter of the turn), filled: ``_filled``."""
    return _filled(tmp_path_factory, "blobs")


@pytest.fixture(scope="module")
def lit_hollows(tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    """48 px GGX hollows (shadows up to 0.41 of the turn), filled: ``_filled``."""
    return _filled(tmp_path_factory, "hollows")


def _filled(tmp_path_factory: pytest.TempPathFactory, scene: str) -> dict[str, object]:
    """A 48 px GGX ``scene`` at 2 ms (reset-at-end) with dualres's evidence on the true normals, the true
    mask, and the same evidence with light filling every super pixel's shadow (an event every FILL_US)."""
    path = tmp_path_factory.mktemp("edges") / f"{scene}.h5"
    simulate(SimulationConfig(scene=scene, size=48, seed=0, refractory_us=2000.0), path)
    capture = psfmt.read(path)
    pre = preprocess(capture, PreprocessOptions())
    gt = capture.ground_truth
    truth = true_shadows(gt.depth, gt.mask, pre.light, pre.t0_us, pre.period_us)
    evidence = pre.evidence.with_normal(np.asarray(gt.normal, dtype=np.float32))
    # the super pixels' shadows on a FILL_US grid: where at least half of their frame pixels are shadowed
    steps = int(T // FILL_US)
    times = pre.t0_us + grid_times(pre.period_us, steps)
    pixels = np.flatnonzero(np.asarray(gt.mask).ravel())
    covering = evidence.super_pixel[pixels]
    n_events = evidence.event_shape[0] * evidence.event_shape[1]
    shadowed = truth.contains_grid(pixels, times).astype(float)
    share = np.stack([np.bincount(covering, weights=row, minlength=n_events) for row in shadowed])
    share /= np.maximum(np.bincount(covering, minlength=n_events), 1)
    inside = share >= 0.5
    # the sensor is refractory for 2 ms after the edge's own event: the fill starts and ends that far inside
    for shift in (-2, -1, 1, 2):
        inside &= np.roll(share >= 0.5, shift, axis=0)
    k, e = np.nonzero(inside)
    width = evidence.event_shape[1]
    events = capture.events.read()
    fill = psfmt.EventArray(e % width, e // width, np.round(times[k]).astype(np.int64), np.where(k % 2 == 0, 1, -1))
    merged = psfmt.EventArray.concatenate([events, fill])
    stream = merged[np.argsort(merged.t, kind="stable")]
    profile = interval_profile(stream, width, t0_us=pre.t0_us, period_us=pre.period_us,
                               contrast_pos=evidence.contrast_pos, contrast_neg=evidence.contrast_neg)
    return {"evidence": evidence, "filled": replace(evidence, profile=profile), "truth": truth, "mask": gt.mask,
            "fill_events": len(fill.t)}


def _fused(evidence: ShadowEvidence, *assignments: str) -> object:
    entry = get_registries().shadow_detectors.get("fused")
    return entry.obj().detect(evidence, entry.parse_options(["height_scale=1", *assignments]))


def test_light_in_a_shadow_hides_it_from_the_dark_spans_but_not_from_its_edges(lit_shadows: dict) -> None:
    """With the fill the dark spans find under half of what they found; the edges give most of it back,
    as precisely."""
    truth, region = lit_shadows["truth"], lit_shadows["mask"]
    assert lit_shadows["fill_events"] > 200  # measured 244
    clean = score(_fused(lit_shadows["evidence"], "edge_share=0"), truth, region)
    dark_only = score(_fused(lit_shadows["filled"], "edge_share=0"), truth, region)
    with_edges = _fused(lit_shadows["filled"])
    both = score(with_edges, truth, region)
    # measured recall 0.87 clean, 0.42 filled, 0.70 filled with the edges; precision 1.00 throughout
    assert clean[1] > 0.8 and dark_only[1] < 0.5
    assert both[1] > dark_only[1] + 0.2 and both[0] > 0.99
    assert 0 < with_edges.diagnostics["edge_seen"] < with_edges.diagnostics["edge_runs"]  # measured 111 of 233


def test_seen_shadows_lie_where_the_surface_predicts_them(lit_shadows: dict) -> None:
    evidence = lit_shadows["filled"]
    seen = seen_shadows(evidence, surface_height(evidence), 360, 0.225, 10.0)
    assert seen.seen.shape == (360, seen.columns.size) and seen.seen.any(axis=0).all()
    assert seen.pixel_share.shape == (np.count_nonzero(lit_shadows["mask"]),)
    assert 0.0 <= seen.pixel_share.min() and seen.pixel_share.max() <= 1.0
    # a flat surface predicts no shadow, so nothing is seen
    flat = evidence.with_normal(np.broadcast_to(np.float32([0, 0, 1]), evidence.normal.shape).copy())
    none = seen_shadows(flat, surface_height(flat), 360, 0.225, 10.0)
    assert none.runs == 0 and none.columns.size == 0 and not none.pixel_share.any()


def test_a_fitted_surface_takes_the_seen_shadows_of_every_pixel(lit_hollows: dict) -> None:
    """``edge_share`` limits the seen shadows on a start's surface, ``fitted_edge_share`` (the whole turn)
    on a fitted one: the same limit gives the same mask either way, and the fitted default adds shadow
    time only at the pixels the surface shadows for more than the start's limit."""
    truth, region, filled = lit_hollows["truth"], lit_hollows["mask"], lit_hollows["filled"]
    fitted = filled.with_normal(filled.normal, fitted=True)
    start = _fused(filled)
    capped = _fused(fitted, "fitted_edge_share=0.3", "edge_share=0")
    whole = _fused(fitted)
    pixels = np.flatnonzero(np.asarray(region).ravel())
    assert np.array_equal(start.coverage()[pixels], capped.coverage()[pixels])
    added = whole.coverage()[pixels] - start.coverage()[pixels]
    seen = seen_shadows(filled, surface_height(filled), 720, 0.225, 10.0)
    assert added.min() >= 0 and added.max() > 0
    assert not added[seen.pixel_share <= 0.3].any()
    # measured recall 0.43 → 0.66, precision 1.00 both
    before, after = score(start, truth, region), score(whole, truth, region)
    assert after[1] > before[1] + 0.15 and after[0] > 0.99


def test_where_inter_reflection_is_taken_out_a_taller_surface_adds_its_confirmed_shadows(lit_hollows: dict) -> None:
    """A surface flattened as inter-reflection flattens one (every tilt × 0.8, so its height × 0.8) casts
    short shadows; told that inter-reflection is taken out, ``fused`` adds the confirmed shadows of the
    surface ``reflected_scale`` times taller, and 1 adds none."""
    truth, region, filled = lit_hollows["truth"], lit_hollows["mask"], lit_hollows["filled"]
    normal = filled.normal.copy()
    normal[..., :2] *= 0.8
    normal /= np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-12)
    flat = filled.with_normal(normal, fitted=True)
    reflected = filled.with_normal(normal, fitted=True, inter_reflected=True)
    plain = _fused(flat)
    pixels = np.flatnonzero(np.asarray(region).ravel())
    assert np.array_equal(_fused(reflected, "reflected_scale=1").coverage()[pixels], plain.coverage()[pixels])
    taller = _fused(reflected, "reflected_scale=1.25")
    added = taller.coverage()[pixels] - plain.coverage()[pixels]
    assert added.min() >= 0 and added.max() > 0
    # measured recall 0.30 → 0.68, precision 1.00 both
    before, after = score(plain, truth, region), score(taller, truth, region)
    assert after[1] > before[1] + 0.3 and after[0] > 0.99


def test_the_height_of_a_surface_is_calibrated_once_for_the_evidence_and_its_copies(lit_hollows: dict,
                                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """A re-detection of the same surface told something else of it (``inter_reflected``) takes the height
    calibrated and the shadows confirmed the first time (``ShadowEvidence.of_surface``), sweeps only the
    taller surface, and gives the mask a fresh evidence gives; another surface, or a copy with other data,
    calibrates again."""
    calls, sweeps = [], []
    calibrate, confirmed = geometry.calibrate, fused._confirmed
    monkeypatch.setattr(geometry, "calibrate", lambda *args, **kwargs: calls.append(1) or calibrate(*args, **kwargs))
    monkeypatch.setattr(fused, "_confirmed", lambda *args, **kwargs: sweeps.append(1) or confirmed(*args, **kwargs))
    evidence = lit_hollows["evidence"]
    evidence.forget()
    fitted = evidence.with_normal(evidence.normal, fitted=True)
    first = _fused(fitted, "height_scale=0")
    again = _fused(fitted.with_normal(fitted.normal.copy(), fitted=True, inter_reflected=True), "height_scale=0",
                   "reflected_scale=1")
    assert len(calls) == 1 and len(sweeps) == 1
    assert np.array_equal(first.coverage(), again.coverage()) and first.diagnostics == again.diagnostics
    taller = _fused(fitted.with_normal(fitted.normal.copy(), fitted=True, inter_reflected=True), "height_scale=0")
    assert len(calls) == 1 and len(sweeps) == 2
    assert np.all(taller.coverage() >= first.coverage())
    tilted = fitted.normal.copy()
    tilted[..., 0] += 0.01
    _fused(fitted.with_normal(tilted, fitted=True), "height_scale=0")
    fresh = _fused(replace(fitted, profile=fitted.profile), "height_scale=0")
    assert len(calls) == 3 and len(sweeps) == 4
    assert np.array_equal(fresh.coverage(), first.coverage())


def test_the_super_pixels_are_made_once_for_the_evidence_and_its_copies(lit_hollows: dict) -> None:
    evidence = lit_hollows["evidence"]
    groups = SuperPixels.shared(evidence)
    assert SuperPixels.shared(evidence.with_normal(evidence.normal, fitted=True)) is groups
    evidence.forget()
    assert SuperPixels.shared(evidence) is groups
    other = np.asarray(evidence.mask).copy()
    other[other.shape[0] // 2 :] = False
    fewer = SuperPixels.shared(replace(evidence, mask=other))
    assert fewer is not groups and fewer.group.size == np.count_nonzero(other) < groups.group.size


def test_forget_drops_what_the_detectors_kept_for_every_copy(lit_hollows: dict, monkeypatch: pytest.MonkeyPatch) -> None:
    calls = []
    calibrate = geometry.calibrate
    monkeypatch.setattr(geometry, "calibrate", lambda *args, **kwargs: calls.append(1) or calibrate(*args, **kwargs))
    evidence = lit_hollows["evidence"]
    evidence.forget()
    fitted = evidence.with_normal(evidence.normal, fitted=True)
    _fused(fitted, "height_scale=0")
    _fused(fitted, "height_scale=0")
    assert len(calls) == 1 and fitted.memo
    evidence.forget()
    assert not fitted.memo
    _fused(fitted, "height_scale=0")
    assert len(calls) == 2


def test_evidence_on_a_device_integrates_and_sweeps_its_surface_there(lit_hollows: dict, monkeypatch: pytest.MonkeyPatch) -> None:
    """A solver on a GPU sets ``ShadowEvidence.device``: the surface's height is solved there
    (``integrate_device``), once per surface, and its shadows swept there (``shadow_sweep_device``), here
    through torch on the CPU (``devices.on_host`` told otherwise). The heights are the host's within
    1e-6 px, the height scale chosen and the masks ``fused`` and ``geometry`` give the host's."""
    import pstoolkit.surface.integrate_device as integrate_device
    from pstoolkit._shared import devices

    solved = []
    solve = integrate_device.integrate_normals_on
    monkeypatch.setattr(integrate_device, "integrate_normals_on", lambda *args: solved.append(1) or solve(*args))
    evidence = lit_hollows["evidence"]
    evidence.forget()
    host_height = integrated_height(evidence)
    host = _fused(evidence, "height_scale=0")
    assert solved == []
    monkeypatch.setattr(devices, "on_host", lambda device: False)
    there = replace(evidence, profile=evidence.profile)
    height = integrated_height(there)
    assert solved == [1] and np.abs(height - host_height).max() < 1e-6 and not height.flags.writeable
    assert integrated_height(there.with_normal(there.normal, fitted=True)) is height and solved == [1]
    mask = _fused(there, "height_scale=0")
    assert mask.diagnostics == host.diagnostics and mask.diagnostics["height_scale"] == 1.0
    assert np.array_equal(mask.coverage(), host.coverage())
    geometry_entry = get_registries().shadow_detectors.get("geometry")
    swept = geometry_entry.obj().detect(there, geometry_entry.parse_options([]))
    monkeypatch.setattr(devices, "on_host", lambda device: True)
    assert np.array_equal(swept.coverage(), geometry_entry.obj().detect(evidence, geometry_entry.parse_options([])).coverage())


def test_fused_on_a_device_confirms_the_hosts_shadows_and_moves_the_dark_map_once(lit_hollows: dict,
                                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """Through torch on the CPU, as on a GPU: a fitted, inter-reflected surface (the seen edges of every
    pixel, rebuilt on the device from the sweep's runs, a few pixels at a time; the taller surface too)
    confirms the host's shadows, and the events' dark map is made once for the capture's detections."""
    from pstoolkit._shared import devices

    filled = lit_hollows["filled"]
    filled.forget()
    surfaces = [filled.with_normal(filled.normal, fitted=True, inter_reflected=True)]
    tilted = filled.normal.copy()
    tilted[..., 0] += 0.02
    surfaces.append(filled.with_normal(tilted, fitted=True, inter_reflected=True))
    host = [_fused(surface, "height_scale=0") for surface in surfaces]
    made = []
    darkness = fused.event_darkness
    monkeypatch.setattr(fused, "event_darkness", lambda *args: made.append(1) or darkness(*args))
    monkeypatch.setattr(devices, "on_host", lambda device: False)
    # chunks of 7 pixels on the default 720 steps
    monkeypatch.setattr(fused, "SEEN_BYTES", 7 * 6 * 721)
    there = replace(filled, profile=filled.profile)
    for surface, expected in zip(surfaces, host, strict=True):
        mask = _fused(there.with_normal(surface.normal, fitted=True, inter_reflected=True), "height_scale=0")
        assert mask.diagnostics == expected.diagnostics and mask.diagnostics["edge_seen"] > 0
        np.testing.assert_array_equal(mask.table.start, expected.table.start)
        np.testing.assert_array_equal(mask.table.end, expected.table.end)
    assert made == [1]
