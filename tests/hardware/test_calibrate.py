"""Event→frame calibration on a simulated LED-array target with a known affine: blob centres,
robust matching with spurious blobs, < 0.1 px error, manual pairs, storing, and the CLI."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from helpers.calibration import TRUE_AFFINE, _gaussians, led_target

import psfmt
from pstoolkit.cli import main
from pstoolkit.errors import UserError
from pstoolkit.hardware.calibrate import (
    apply_affine,
    blob_centres,
    calibrate_target,
    fit_affine,
    match_affine,
)


def _error_px(affine: np.ndarray) -> float:
    """Largest frame-pixel distance between the fitted and the true map over the event sensor."""
    v, u = np.mgrid[0:32, 0:32].astype(np.float64)
    grid = np.stack([u.ravel(), v.ravel()], axis=1)
    return float(np.linalg.norm(apply_affine(affine, grid) - apply_affine(TRUE_AFFINE, grid), axis=1).max())


def test_blob_centres_are_subpixel() -> None:
    centres = np.array([[10.3, 7.8], [20.71, 21.45]])
    found = blob_centres(_gaussians((32, 32), centres, 1.0, 100.0))
    assert np.abs(found[np.argsort(found[:, 0])] - centres).max() < 0.01


def test_the_led_target_gives_the_known_affine_within_a_tenth_of_a_pixel(tmp_path: Path) -> None:
    with psfmt.read(led_target(tmp_path / "target.h5")) as capture:
        fit = calibrate_target(capture)
    assert (fit.frame_blobs, fit.event_blobs, fit.pairs) == (26, 26, 25)  # the spurious blobs stay unmatched
    assert _error_px(fit.affine) < 0.1
    assert fit.rms_px < 0.1 and fit.max_px < 0.2


def test_matching_survives_shuffled_and_missing_points() -> None:
    rng = np.random.default_rng(3)
    frame = rng.uniform(5, 60, (20, 2))
    inverse = np.linalg.inv(np.vstack([TRUE_AFFINE, [0, 0, 1]]))[:2]
    event = apply_affine(inverse, frame[3:])[rng.permutation(17)]  # three LEDs missing in the events
    fit = match_affine(event, frame, psfmt.scale_affine(0.5))
    assert fit.pairs == 17 and np.abs(fit.affine - TRUE_AFFINE).max() < 1e-9


def test_manual_pairs_and_their_errors() -> None:
    event = np.array([[1.0, 1.0], [10.0, 2.0], [4.0, 9.0], [8.0, 8.0]])
    fit = fit_affine(event, apply_affine(TRUE_AFFINE, event))
    assert np.abs(fit.affine - TRUE_AFFINE).max() < 1e-12 and fit.rms_px < 1e-12
    with pytest.raises(UserError, match=r"^calibration: an affine needs at least 3 point pairs, got 2$"):
        fit_affine(event[:2], event[:2])
    with pytest.raises(UserError, match=r"^calibration: the event points lie on one line, so the affine is undetermined$"):
        fit_affine(np.array([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]]), np.zeros((3, 2)))


def test_calibrate_command_stores_the_affine_atomically(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    target = led_target(tmp_path / "target.h5")
    other = led_target(tmp_path / "scene.h5", seed=1)
    assert main(["calibrate", "affine", str(target), "--apply-to", str(other)]) == 0
    line = capsys.readouterr().out.strip()
    assert line.startswith("event→frame affine from 25 LED pairs (26 frame blobs, 26 event blobs): reprojection error RMS 0.0")
    assert line.endswith(f"stored in {target}, {other}")
    for path in (target, other):
        with psfmt.read(path) as capture:
            assert _error_px(capture.calibration.event_to_frame) < 0.1
            assert capture.ground_truth is not None and capture.frames.count == 2  # the rest is kept
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.h5", "target.h5"]


def test_calibrate_command_with_manual_pairs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    target = led_target(tmp_path / "target.h5")
    event = np.array([[1.0, 1.0], [10.0, 2.0], [4.0, 9.0]])
    pairs = tmp_path / "pairs.txt"
    pairs.write_text("# u_e v_e u_f v_f\n" + "\n".join(" ".join(f"{x:.9f}" for x in row) for row in np.hstack([event, apply_affine(TRUE_AFFINE, event)])))
    assert main(["calibrate", "affine", str(target), "--pairs", str(pairs), "--no-store"]) == 0
    assert "from 3 manual pairs" in capsys.readouterr().out
    with psfmt.read(target) as capture:
        assert capture.calibration.event_to_frame is None


def test_calibrate_command_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    target = led_target(tmp_path / "target.h5")
    bad = tmp_path / "pairs.txt"
    bad.write_text("1 2 3\n")
    cases = [
        (["calibrate", "affine", str(tmp_path / "none.h5")], f"{tmp_path / 'none.h5'}: does not exist"),
        (["calibrate", "affine", str(target), "--pairs", str(bad)], f"{bad}: expected lines of 'u_event v_event u_frame v_frame', got 3 column(s)"),
        (["calibrate", "affine", str(target), "--max-error-px", "0.001"], "reprojection error RMS"),
        (["calibrate", "affine", str(target), "--frame", "5"], "--frame 5: the capture has 2 frames"),
    ]
    for argv, message in cases:
        assert main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("pstoolkit: error: ") and message in err[0]
    with psfmt.read(target) as capture:
        assert capture.calibration.event_to_frame is None
