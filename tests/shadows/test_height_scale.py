"""The height scale the surface detectors march at (``pstoolkit.shadows.height_scale``): event onsets,
the choice among scales, and the calibration on simulated blobs whose surface was flattened or
heightened by a known factor."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from helpers.event_rows import event_stream

import psfmt
from pstoolkit.plugin.manager import get_registries
from pstoolkit.shadows import ShadowEvidence, interval_profile
from pstoolkit.shadows.height_scale import COARSE_SCALES, MIN_AGREEMENT, _choose, calibrate, onsets
from pstoolkit.shadows.score import score, true_shadows
from pstoolkit.shadows.surface_sweep import surface_height
from pstoolkit.sim.config import SimulationConfig
from pstoolkit.sim.simulator import simulate
from pstoolkit_dualres.preprocess import PreprocessOptions, preprocess

T = 33_333.0


def _phases(keys: np.ndarray, pixel: int) -> list[float]:
    """The on-time copies of one pixel's onset keys, as phases."""
    base = pixel * 3.0 * T + T
    return sorted(float(k - base) for k in keys if base <= k < base + T)


def test_onsets_are_the_first_events_of_runs() -> None:
    rows = [
        # R = 2 ms: the falling event 2 ms after another continues its run; a polarity change starts one
        [(1000.0, -1), (3000.0, -1), (3500.0, 1), (9000.0, 1)],
        # a burst (R = 0 would fire it) starts one run only
        [(5000.0, -1), (5010.0, -1), (5020.0, -1), (20_000.0, 1)],
    ]
    profile = interval_profile(event_stream(rows), 2, t0_us=0.0, period_us=T, contrast_pos=0.15, contrast_neg=0.15)
    falling, rising = onsets(profile, 2000.0)
    assert _phases(falling, 0) == [1000.0] and _phases(rising, 0) == [3500.0, 9000.0]
    assert _phases(falling, 1) == [5000.0] and _phases(rising, 1) == [20_000.0]
    # each onset is also entered a period early and late, so a search across the period's ends finds it
    assert len(falling) == 3 * 2 and np.all(np.diff(falling) > 0)
    falling, _ = onsets(profile, 0.0)
    assert _phases(falling, 1) == [5000.0]  # the burst's events lie within 200 µs of each other


def test_the_choice_keeps_1_unless_another_scale_earns_it() -> None:
    scales = (0.5, 0.75, 1.0, 1.5, 2.0)
    # a clear, interior best far above 1's: taken
    assert _choose(scales, [500] * 5, [0.1, 0.2, 0.3, 0.6, 0.4]) == 1.5
    # a best within MIN_GAIN of 1's: 1 stays
    assert _choose(scales, [5000] * 5, [0.1, 0.2, 0.58, 0.6, 0.4]) == 1.0
    # agreement too low to act on, though far above 1's
    assert _choose(scales, [500] * 5, [0.0, 0.0, -0.2, MIN_AGREEMENT - 0.05, 0.0]) == 1.0
    # the best at an end of the range: it may lie beyond, so nothing is changed
    assert _choose(scales, [500] * 5, [0.1, 0.2, 0.3, 0.5, 0.7]) == 1.0
    # 1 predicts no edges at all: the others are judged against no agreement
    assert _choose(scales, [0, 0, 0, 500, 500], [0.0, 0.0, 0.0, 0.6, 0.4]) == 1.5
    # of the scales within two standard errors of the best, the one nearest 1
    assert _choose((1.0, 1.2, 1.5, 2.0), [0, 500, 500, 500], [0.0, 0.57, 0.6, 0.4]) == 1.2
    # under MIN_EDGES predicted edges a scale does not count
    assert _choose(scales, [500, 500, 500, 10, 500], [0.1, 0.2, 0.3, 0.9, 0.4]) == 1.0


@pytest.fixture(scope="module")
def blobs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[psfmt.Capture, ShadowEvidence, object]]:
    """48 px GGX blobs at 2 ms under both refractory rules, with dualres's evidence and the true mask."""
    out = {}
    for rule in ("reset-at-end", "rate-limited"):
        path = tmp_path_factory.mktemp("height") / f"{rule}.h5"
        simulate(SimulationConfig(scene="blobs", size=48, seed=0, refractory_us=2000.0, refractory_rule=rule), path)
        capture = psfmt.read(path)
        pre = preprocess(capture, PreprocessOptions())
        gt = capture.ground_truth
        out[rule] = (capture, pre.evidence, true_shadows(gt.depth, gt.mask, pre.light, pre.t0_us, pre.period_us))
    return out


def _scaled_normals(normal: np.ndarray, factor: float) -> np.ndarray:
    """The normals of the same surface with its height times ``factor``."""
    scaled = np.asarray(normal, dtype=np.float32) * np.array([factor, factor, 1.0], dtype=np.float32)
    return scaled / np.linalg.norm(scaled, axis=-1, keepdims=True)


@pytest.mark.parametrize(("factor", "low", "high"), [(0.7, 1.3, 1.55), (1.0, 1.0, 1.0), (1.3, 0.7, 0.85)])
def test_the_events_find_the_height_a_surface_lacks(blobs: dict, factor: float, low: float, high: float) -> None:
    """Blobs flattened to 0.7 of their height cast almost none of their shadows; the onsets of the
    events at the shadows' edges say by how much (1/0.7 = 1.43), and the detector's mask comes back."""
    capture, evidence, truth = blobs["reset-at-end"]
    evidence = evidence.with_normal(_scaled_normals(capture.ground_truth.normal, factor))
    chosen = calibrate(evidence, surface_height(evidence), margin_px=0.225)
    assert low <= chosen.scale <= high  # measured 1.41, 1.00, 0.77
    assert chosen.scales == tuple(sorted(chosen.scales)) and len(chosen.edges) == len(chosen.scales)
    assert set(COARSE_SCALES) <= set(chosen.scales)
    entry = get_registries().shadow_detectors.get("geometry")
    as_is = score(entry.obj().detect(evidence, entry.parse_options(["height_scale=1"])), truth, capture.ground_truth.mask)
    mask = entry.obj().detect(evidence, entry.parse_options([]))
    calibrated = score(mask, truth, capture.ground_truth.mask)
    assert mask.diagnostics["height_scale"] == pytest.approx(chosen.scale, abs=1e-3)
    if factor < 1:
        assert as_is[1] < 0.1 and calibrated[1] > 0.85 and calibrated[0] > 0.95  # recall 0.04 -> 0.94, precision 1.00
    elif factor > 1:
        assert as_is[0] < 0.5 and calibrated[0] > 0.95 and calibrated[1] > 0.9  # precision 0.44 -> 1.00, recall 0.98


def test_where_the_onsets_carry_no_edges_the_surface_stays(blobs: dict) -> None:
    """Under the rate-limited rule these blobs fire every refractory period for most of the turn, so a
    shadow's edge starts no run: no scale reaches the agreement to act on, and the flattened surface is
    marched as it is (the calibration does no harm where it cannot help)."""
    capture, evidence, _ = blobs["rate-limited"]
    evidence = evidence.with_normal(_scaled_normals(capture.ground_truth.normal, 0.7))
    chosen = calibrate(evidence, surface_height(evidence), margin_px=0.225)
    assert chosen.scale == 1.0 and max(chosen.matched) < MIN_AGREEMENT  # measured at most 0.16
    fixed = get_registries().shadow_detectors.get("fused")
    assert fixed.obj().detect(evidence, fixed.parse_options(["height_scale=1.5", "edge_share=0"])).diagnostics == {"height_scale": 1.5}


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.cuda)])
def test_the_device_calibration_is_the_hosts(blobs: dict, device: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """On a device the calibration scores the edges where its tracker keeps them (``kappa_there``, the
    torch copy of ``_kappa``): the same agreements to rounding and the same scale, here for the flattened
    blobs whose scale moves (through torch on the CPU, ``devices.on_host`` told otherwise, and on a GPU)."""
    from pstoolkit._shared import devices
    from pstoolkit.shadows import height_scale

    capture, evidence, _ = blobs["reset-at-end"]
    evidence = evidence.with_normal(_scaled_normals(capture.ground_truth.normal, 0.7))
    host = calibrate(evidence, surface_height(evidence), margin_px=0.225)
    scored = []
    real = height_scale.kappa_there
    monkeypatch.setattr(height_scale, "kappa_there", lambda *args: scored.append(1) or real(*args))
    monkeypatch.setattr(devices, "on_host", lambda name: False)
    there = calibrate(dataclasses.replace(evidence, device=device), surface_height(evidence), margin_px=0.225)
    assert len(scored) == len(host.scales) and there.scale == host.scale != 1.0
    assert there.scales == host.scales and there.edges == host.edges
    np.testing.assert_allclose(there.matched, host.matched, rtol=1e-12, atol=1e-12)
    # the onsets are found and moved to the device once for every surface of the evidence
    found = []
    monkeypatch.setattr(height_scale, "onsets", lambda *args: found.append(1) or onsets(*args))
    moved = dataclasses.replace(evidence, device=device)
    for factor in (0.7, 0.8):
        calibrate(moved.with_normal(_scaled_normals(capture.ground_truth.normal, factor)), surface_height(evidence), margin_px=0.225)
    assert found == [1]
