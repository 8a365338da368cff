"""The package layout: subpackages by job and light imports."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from helpers import REPO

ROOT = REPO


def test_the_package_folder_holds_subpackages_and_four_modules() -> None:
    modules = sorted(p.name for p in (REPO / "pstoolkit").glob("*.py"))
    assert modules == ["__init__.py", "errors.py", "grid.py", "testing.py"]
    packages = sorted(p.name for p in (REPO / "pstoolkit").iterdir() if (p / "__init__.py").exists())
    assert packages == ["_shared", "cli", "evaluation", "events", "hardware", "io", "optics", "plugin", "shadows", "sim", "solve", "surface", "view"]


def test_pstoolkit_exports_what_a_plugin_needs() -> None:
    import pstoolkit
    from pstoolkit.optics.brdf import BRDF
    from pstoolkit.solve.base import Progress

    assert pstoolkit.BRDF is BRDF and pstoolkit.Progress is Progress
    missing = [name for name in pstoolkit.__all__ if not hasattr(pstoolkit, name)]
    assert missing == []
    with pytest.raises(AttributeError, match="has no attribute 'nothing'"):
        pstoolkit.nothing  # noqa: B018


def test_the_package_its_subpackages_the_cli_and_the_diligent_converter_load_neither_torch_nor_numba() -> None:
    packages = ["pstoolkit", "pstoolkit.cli", "pstoolkit.plugin", "pstoolkit.optics", "pstoolkit.events", "pstoolkit.sim", "pstoolkit.solve",
                "pstoolkit.shadows", "pstoolkit.surface", "pstoolkit.evaluation", "pstoolkit.hardware", "pstoolkit.io", "pstoolkit.view", "pstoolkit.grid",
                "pstoolkit.sim.timing", "pstoolkit.sim.exposure", "pstoolkit_diligent.converters"]
    code = f"import sys\nfor p in {packages!r}: __import__(p)\nprint(sorted({{'torch', 'numba', 'matplotlib'}} & set(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_ruff_finds_nothing_with_the_configured_rules() -> None:
    ruff = shutil.which("ruff") or str(Path(sys.executable).with_name("ruff"))
    if not Path(ruff).exists():
        pytest.skip("ruff is not installed (pip install -e '.[test]')")
    done = subprocess.run([ruff, "check", "--no-cache", str(ROOT)], capture_output=True, text=True)
    assert done.returncode == 0, done.stdout[-3000:]
