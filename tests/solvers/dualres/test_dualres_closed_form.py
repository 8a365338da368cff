"""Supplement Table 1 "from super pixels": normals of the super pixels from their events alone
(EventPS relation), bilinearly interpolated to frame pixels, fix the free degree of freedom of
frame pixels with two effective lights better than a fill from frame pixels with three."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

import psfmt
from pstoolkit import GREY_WEIGHTS, ShadowMask
from pstoolkit.evaluation.metrics import angular_error_deg
from pstoolkit.grid import bilinear_taps, to_frames
from pstoolkit.optics.equivalent import sample_times
from pstoolkit.plugin.options import defaults
from pstoolkit.shadows.fused import FusedDetector
from pstoolkit_dualres import closed_form_device
from pstoolkit_dualres.closed_form import closed_form
from pstoolkit_dualres.closed_form_device import device_fixed_point
from pstoolkit_dualres.fixed_point import FixedPoint, fixed_point
from pstoolkit_dualres.preprocess import Preprocessed, PreprocessOptions, preprocess
from pstoolkit_dualres.super_pixel_normals import event_normals


@pytest.fixture(scope="module")
def sphere(sphere_48: Path) -> tuple[psfmt.Capture, Preprocessed]:
    capture = psfmt.read(sphere_48)
    return capture, preprocess(capture, PreprocessOptions())


def _super_normals(pre: Preprocessed) -> tuple[np.ndarray, np.ndarray]:
    events = pre.events
    return event_normals(events.pixel, events.t_ref_us, events.t_us, events.target, events.weight, pre.light,
                         n_pixels=pre.event_height * pre.event_width)


def test_super_pixel_normals_from_events(sphere: tuple[psfmt.Capture, Preprocessed]) -> None:
    capture, pre = sphere
    gt = capture.ground_truth
    normal, known = _super_normals(pre)
    he, we = pre.event_height, pre.event_width
    truth = gt.normal.reshape(he, 2, we, 2, 3).mean(axis=(1, 3)).reshape(-1, 3)
    truth /= np.linalg.norm(truth, axis=1, keepdims=True) + 1e-12
    inside = gt.mask.reshape(he, 2, we, 2).all(axis=(1, 3)).ravel()
    assert known[inside].mean() > 0.9  # measured 0.96
    error = np.degrees(np.arccos(np.clip(np.sum(normal * truth, axis=1), -1.0, 1.0)))
    assert error[inside & known].mean() < 2.5  # measured 1.42° (GGX highlights break the Lambertian ratio a little)
    assert np.all(normal[~known] == 0.0) and np.allclose(np.linalg.norm(normal[known], axis=1), 1.0)


def test_two_light_pixels_take_their_free_direction_from_the_super_pixels(sphere: tuple[psfmt.Capture, Preprocessed]) -> None:
    capture, pre = sphere
    gt = capture.ground_truth
    normal, known = _super_normals(pre)
    interpolated = to_frames(normal, known, pre.event_to_frame, pre.height, pre.width, pre.event_height, pre.event_width)[0]
    options = PreprocessOptions()

    def init(super_normal: np.ndarray | None) -> np.ndarray:
        return closed_form(pre.per_window, pre.windows_us + pre.t0_us, pre.mask, pre.light, visibility=None,
                           iterations=options.init_iterations, n_samples=options.light_samples,
                           super_normal=super_normal).normal

    with_events = init(interpolated.reshape(pre.height, pre.width, 3))
    np.testing.assert_array_equal(with_events, pre.init.normal)  # what preprocessing does: the same code path
    frames_only = init(None)
    two = gt.mask & (pre.init.effective == 2)
    assert two.sum() > 30  # measured 49 rim pixels
    err_events = angular_error_deg(with_events, gt.normal, gt.mask)[two].mean()
    err_frames = angular_error_deg(frames_only, gt.normal, gt.mask)[two].mean()
    assert err_events < 0.5 * err_frames  # measured 2.91° vs 7.65°
    three = gt.mask & (pre.init.effective == 3)
    np.testing.assert_array_equal(with_events[three], frames_only[three])


def test_bilinear_interpolation_uses_only_known_super_pixels() -> None:
    index, weight = bilinear_taps(np.array([0.25]), np.array([0.5]), 2, 2)
    np.testing.assert_array_equal(index, [[0, 1, 2, 3]])
    np.testing.assert_allclose(weight, [[0.375, 0.125, 0.375, 0.125]])
    values = np.array([[1.0], [5.0], [3.0], [100.0]])
    known = np.array([True, True, True, False])
    affine = psfmt.scale_affine(0.5)
    out, ok = to_frames(values, known, affine, 4, 4, 2, 2)
    # the corner frame pixel clamps onto the unknown super pixel alone
    np.testing.assert_array_equal(ok, np.arange(16) != 15)
    # frame pixel (u 1, v 1) sits at event (0.25, 0.25): weights 9/16, 3/16, 3/16 and the unknown 1/16 dropped
    assert out.reshape(4, 4)[1, 1] == pytest.approx((9 * 1.0 + 3 * 5.0 + 3 * 3.0) / 15)
    none, ok = to_frames(values, np.zeros(4, dtype=bool), affine, 4, 4, 2, 2)
    assert not ok.any() and np.all(none == 0.0)


def _fixed_points(pre: Preprocessed, shadows: ShadowMask | None, device: str) -> tuple[FixedPoint, FixedPoint, np.ndarray]:
    """The fixed point of ``pre``'s window means under ``shadows`` on the host and through torch on ``device``."""
    options = PreprocessOptions()
    pixels = np.flatnonzero(pre.mask)
    grey = pre.per_window.reshape(len(pre.windows_us), -1, 3)[:, pixels] @ np.asarray(GREY_WEIGHTS)
    windows = pre.windows_us + pre.t0_us
    masks = None if shadows is None else [~shadows.contains_grid(pixels, sample_times(t0, t1, options.light_samples))
                                          for t0, t1 in windows]
    common = {"iterations": options.init_iterations, "n_samples": options.light_samples}
    return (fixed_point(pre.light, windows, grey, masks, **common),
            device_fixed_point(pre.light, windows, grey, masks, device=device, **common), grey)


def test_the_device_iteration_is_the_same_in_batches_of_any_size(sphere: tuple[psfmt.Capture, Preprocessed],
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    """The 3×3 systems go to torch ``LINALG_BATCH`` at a time (cuSOLVER fails on one call of 65 536
    eigenvalue problems): batches of another size give the same fixed point, bit for bit."""
    whole = _fixed_points(sphere[1], None, "cpu")[1]
    eigvalsh, solve, sizes = torch.linalg.eigvalsh, torch.linalg.solve, []
    monkeypatch.setattr(torch.linalg, "eigvalsh", lambda matrices: sizes.append(len(matrices)) or eigvalsh(matrices))
    monkeypatch.setattr(torch.linalg, "solve", lambda a, b: sizes.append(len(a)) or solve(a, b))
    monkeypatch.setattr(closed_form_device, "LINALG_BATCH", 97)
    split = _fixed_points(sphere[1], None, "cpu")[1]
    assert max(sizes) == 97 and len(sizes) > 4 * whole.iterations
    for name in ("normal", "effective", "solved"):
        np.testing.assert_array_equal(getattr(split, name), getattr(whole, name), err_msg=name)


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.cuda)])
@pytest.mark.parametrize("scene", ["sphere", "blobs"])
def test_the_device_iteration_is_the_hosts_to_rounding(scene: str, device: str, sphere: tuple[psfmt.Capture, Preprocessed],
                                                       blobs_48: Path) -> None:
    """The torch copy of the fixed point (``closed_form_device``, what a GPU runs) held to the numpy one,
    through torch on the CPU and on a GPU: the sphere without a mask, the blobs under the cast shadows
    ``fused`` finds on the closed form's surface; the lights it keeps give the same albedo and two-light
    planes."""
    if scene == "sphere":
        pre, shadows = sphere[1], None
    else:
        pre = preprocess(psfmt.read(blobs_48), PreprocessOptions())
        shadows = FusedDetector().detect(pre.evidence.with_normal(pre.init.normal), defaults(FusedDetector.options))
        assert len(shadows) > 100
    host, torch_run, grey = _fixed_points(pre, shadows, device)
    assert host.iterations == torch_run.iterations and host.iterations >= 3
    # The iteration takes some rim pixels onto the terminator of one light sample (l·n ≈ 1e-16), so
    # rounding tells whether that window's light is one sample's share or none, and whether it counts
    # as effective: the normals there, and of the pixels that passed there, agree to 0.02°, the others
    # to rounding.
    differ = np.any(host.effective != torch_run.effective, axis=0)
    apart = np.abs(torch_run.normal - host.normal).max(axis=1)
    assert differ.mean() < 0.02 and np.mean(apart > 1e-9) < 0.02  # measured 16 and 18 of 1468 sphere pixels
    np.testing.assert_array_equal(host.solved[~differ], torch_run.solved[~differ])
    assert apart.max() < 3e-4
    rgb = pre.per_window.reshape(len(pre.windows_us), -1, 3)[:, np.flatnonzero(pre.mask)]
    np.testing.assert_allclose(torch_run.lights.albedo(rgb, host.effective, host.normal)[~differ],
                               host.lights.albedo(rgb, host.effective, host.normal)[~differ], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(torch_run.lights.grey_at(~differ), host.lights.grey_at(~differ), rtol=1e-9, atol=1e-15)
    positions = np.flatnonzero(~differ)[::7]
    np.testing.assert_allclose(torch_run.lights.grey_at(positions), host.lights.grey_at(positions), rtol=1e-9, atol=1e-15)
    assert grey.shape[1] == host.normal.shape[0]
