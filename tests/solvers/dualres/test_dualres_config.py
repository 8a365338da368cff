"""dualres and reproducible runs (issue 24, part B): the options a run records are the values it used
(the preset expanded, the shadow detector's options listed), ``pstoolkit run --config result.json``
repeats a run, and ``smoothness`` with the MLP preset, which has nothing to smooth, is refused."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pstoolkit.cli import main
from pstoolkit.errors import UserError
from pstoolkit.plugin.manager import get_registries
from pstoolkit.solve.base import resolve_options
from pstoolkit.solve.batch import solver_options
from pstoolkit_dualres.presets import OVERRIDES, PRESETS

FUSED = ("time_steps=720", "margin_px=0.225", "height_scale=0.0", "edge_tolerance_deg=10.0", "min_gap_ms=-1.0", "edge_share=0.3",
         "fitted_edge_share=1.0", "reflected_scale=1.19")
"""The default shadow detector's options at their defaults, as a run records them."""


def _resolved(*assignments: str) -> dict:
    entry = get_registries().solvers.get("dualres")
    return resolve_options(entry, entry.parse_options(list(assignments)))


def test_the_preset_is_expanded_into_the_options_and_resolving_again_changes_nothing() -> None:
    entry = get_registries().solvers.get("dualres")
    parsed = entry.parse_options(["epochs=2", "shadow.margin_px=0.5"])
    resolved = resolve_options(entry, parsed)
    fast = PRESETS["fast"]
    assert resolved == {
        **parsed, **{name: getattr(fast, name) for name in OVERRIDES}, "epochs": 2,
        "shadow": ("time_steps=720", "margin_px=0.5", "height_scale=0.0", "edge_tolerance_deg=10.0", "min_gap_ms=-1.0", "edge_share=0.3",
                   "fitted_edge_share=1.0", "reflected_scale=1.19"),
    }
    assert resolved["lr"] == 0.005 and resolved["event_weight"] == 8.0 and resolved["frame_samples"] == 8
    assert resolve_options(entry, resolved) == resolved
    paper = _resolved("preset=paper", "lr=0.002")
    assert (paper["epochs"], paper["lr"], paper["batch_pixels"], paper["smoothness"]) == (1200, 0.002, 512, 0.0)
    assert resolve_options(entry, paper) == paper
    # a batch plans its pairs with the resolved options too (what a rerun compares)
    assert solver_options(["dualres"], ["epochs=2"])["dualres"] == _resolved("epochs=2")


def test_smoothness_with_the_mlp_preset_is_an_error() -> None:
    with pytest.raises(UserError, match=(r"^dualres: option smoothness=3 cannot apply with preset=paper: it weighs the "
                                         r"pyramid's finer levels, and this preset's field is an MLP \(no pyramid\)$")):
        _resolved("preset=paper", "smoothness=3")
    assert _resolved("preset=paper", "smoothness=0")["smoothness"] == 0.0  # the preset's own value, as recorded


def test_compile_with_full_batch_steps_is_an_error() -> None:
    with pytest.raises(UserError, match=(r"^dualres: option compile=true cannot apply with full-batch steps \(batch_pixels=0, as "
                                         r"in preset=fast\): it compiles the mini-batch steps; set batch_pixels or preset=paper$")):
        _resolved("compile=true")
    assert _resolved("preset=paper", "compile=true")["compile"] is True
    assert _resolved("compile=true", "batch_pixels=256")["batch_pixels"] == 256


def test_result_json_repeats_a_dualres_run(sphere_48: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Two epochs on the 48 px sphere, then the run again from its result.json: the same normal map
    within float noise (1e-6; measured bit-equal on the CPU, where torch's deterministic kernels
    are on — the tolerance leaves room for another thread count's summation order)."""
    first, again = tmp_path / "first", tmp_path / "again"
    assert main(["run", str(sphere_48), "--solver", "dualres", "--set", "epochs=2", "-o", str(first), "--device", "cpu", "--json"]) == 0
    recorded = json.loads((first / "result.json").read_text())
    options = recorded["options"]
    assert {name: options[name] for name in OVERRIDES} == {**{name: getattr(PRESETS["fast"], name) for name in OVERRIDES}, "epochs": 2}
    assert options["shadow"] == list(FUSED)
    assert not any(isinstance(v, (int, float)) and not isinstance(v, bool) and v < 0 for v in options.values())
    assert main(["run", "--config", str(first / "result.json"), "-o", str(again), "--device", "cpu", "--json"]) == 0
    repeated = json.loads((again / "result.json").read_text())
    assert repeated["options"] == options and repeated["capture_sha256"] == recorded["capture_sha256"]
    np.testing.assert_allclose(np.load(again / "normal.npy"), np.load(first / "normal.npy"), rtol=0, atol=1e-6)
    np.testing.assert_allclose(np.load(again / "roughness.npy"), np.load(first / "roughness.npy"), rtol=0, atol=1e-6)
