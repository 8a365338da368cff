"""The report's figures and HTML (issue 24, part C, item 3): one point per object and solver on the
MAE-against-data-rate plot, colour bars with units on the error and depth maps, a ground-truth column
from the captures given with ``--ground-truth`` (and only from those), and HTML rendered by
markdown-it-py with raw HTML off."""

from __future__ import annotations

import html
import json
import re
import shutil
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from helpers import REPO

import psfmt
import pstoolkit
from pstoolkit.cli import main
from pstoolkit.evaluation.report import mae_rate_figure, maps_figure, markdown_to_html, read_truths
from pstoolkit.evaluation.scoring import Record, collect
from pstoolkit.io.normalmap import normal_to_rgb
from pstoolkit.testing import sphere_capture

if sys.version_info >= (3, 11):
    import tomllib
else:  # Python 3.10: tomli is the same parser
    import tomli as tomllib


def _record(obj: str, solver: str, mae: float | None, rate: float | None) -> Record:
    return Record(obj, solver, mae, None, None, None, None, None, None, rate, 1.0, None, "unused")


def test_the_mae_plot_has_one_point_per_object_and_solver_at_its_own_data_rate() -> None:
    """Before, a solver's captures of different data rates were averaged into one point that sat at
    a rate no capture had; now every (object, solver) is its own point."""
    records = [
        _record("ball", "frameps", 2.0, 0.5), _record("cat", "frameps", 4.0, 1.0), _record("pot", "frameps", 3.0, 0.25),
        _record("ball", "eventps", 6.0, 0.12), _record("cat", "eventps", 8.0, 0.2), _record("pot", "eventps", None, 0.3),
        _record("pot", "dualres", 1.5, None),
    ]
    fig = mae_rate_figure(records)
    (ax,) = fig.axes
    points = sorted(tuple(map(float, xy)) for collection in ax.collections for xy in collection.get_offsets())
    assert points == sorted((100 * r.data_rate, r.mae_deg) for r in records if r.mae_deg is not None and r.data_rate is not None)
    solvers, objects = fig.legends
    assert [t.get_text() for t in solvers.get_texts()] == ["eventps", "frameps"]
    assert [t.get_text() for t in objects.get_texts()] == ["ball", "cat", "pot"]
    markers = {(c.get_facecolor()[0][:3].round(3).tobytes(), c.get_paths()[0].vertices.round(3).tobytes()) for c in ax.collections}
    assert len(markers) == 5  # a colour per solver × a marker per object


@pytest.fixture(scope="module")
def results(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A folder of two result folders of the sphere capture ``ball.h5`` (frameps, and frameps robust
    named ``robust``), the first with a depth map of an orthographic surface; and the capture."""
    root = tmp_path_factory.mktemp("figures")
    capture = sphere_capture(root / "ball.h5", size=32)
    folders = root / "results"
    pstoolkit.solve_capture(capture, "frameps", device="cpu").write(folders / "ball-frameps")
    solved = pstoolkit.solve_capture(capture, "frameps", device="cpu", robust=True)
    solved.write(folders / "ball-robust", name="robust")
    surface = solved.integrate("poisson")
    np.save(folders / "ball-frameps" / "depth.npy", np.where(surface.mask, surface.depth, np.nan).astype(np.float32))
    summary = json.loads((folders / "ball-frameps" / "result.json").read_text())
    summary["surface"] = {"projection": "orthographic", "depth_error": None}
    (folders / "ball-frameps" / "result.json").write_text(json.dumps(summary))
    return folders, capture


def _colour_bar_labels(fig: object) -> list[str]:
    return sorted(ax.get_ylabel() for ax in fig.axes if ax.get_ylabel())  # type: ignore[attr-defined]


def test_error_and_depth_maps_have_colour_bars_with_units(results: tuple[Path, Path]) -> None:
    folders, _ = results
    fig = maps_figure(collect([folders]))
    assert _colour_bar_labels(fig) == ["angular error (°)", "angular error (°)", "z (frame pixels)"]
    bars = [ax for ax in fig.axes if ax.get_ylabel() == "angular error (°)"]
    assert all(ax.get_ylim() == pytest.approx((0.0, 30.0)) for ax in bars)  # the folder's error scale, in degrees


def test_the_ground_truth_column_comes_from_the_captures_given(results: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    folders, capture = results
    records = collect([folders])
    truth = read_truths([capture], ["ball"])["ball"]
    fig = maps_figure(records, truth)
    first = fig.axes[0]
    assert first.get_title() == "ground truth\n(normals)"
    gt = psfmt.load(capture).ground_truth
    np.testing.assert_array_equal(first.images[0].get_array(), normal_to_rgb(gt.normal, gt.mask, bits=8))
    assert _colour_bar_labels(fig) == ["angular error (°)", "angular error (°)", "true z (mm)", "z (frame pixels)"]

    report = tmp_path / "with" / "r.md"
    assert main(["report", str(folders), "-o", str(report), "--ground-truth", str(capture)]) == 0
    image = cv2.imread(str(report.parent / "r-maps-000-ball.png"))
    assert (image.shape[1], image.shape[0]) == (3 * 240, 3 * 260)  # truth + two solvers; normals, errors, depth
    text = report.read_text()
    assert f"The first column is the ground truth of the capture given for the object: ball ({capture})." in text
    # without --ground-truth the capture named in each result.json is not opened: no truth column
    plain = tmp_path / "without" / "r.md"
    assert main(["report", str(folders), "-o", str(plain)]) == 0
    image = cv2.imread(str(plain.parent / "r-maps-000-ball.png"))
    assert image.shape[1] == 2 * 240 and "ground truth of the capture" not in plain.read_text()
    capsys.readouterr()


def test_ground_truth_that_does_not_fit_is_refused(results: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    folders, capture = results
    other = sphere_capture(tmp_path / "cat.h5", size=16)
    blind = tmp_path / "blind" / "ball.h5"
    blind.parent.mkdir()
    psfmt.write(psfmt.Capture(frames=psfmt.load(capture).frames), blind)
    small = tmp_path / "small" / "ball.h5"
    small.parent.mkdir()
    shutil.copy(other, small)
    cases = {
        (str(other),): f"--ground-truth {other}: no result is of object 'cat' (objects: ball)",
        (str(capture), str(capture)): f"--ground-truth {capture}: a second capture of object 'ball' (the first: {capture})",
        (str(blind),): f"--ground-truth {blind}: the capture holds no ground-truth normals",
        (str(small),): f"--ground-truth {small}: its normals are 16×16, the result in {folders / 'ball-frameps'} 32×32 (not the capture of this result?)",
    }
    for captures, message in cases.items():
        args = [arg for path in captures for arg in ("--ground-truth", path)]
        assert main(["report", str(folders), "-o", str(tmp_path / "r.md"), *args]) == 2
        assert capsys.readouterr().err == f"pstoolkit: error: {message}\n"


def test_the_html_is_rendered_by_markdown_it() -> None:
    """The page comes from a CommonMark renderer (emphasis, code blocks, escapes — constructs the old
    regex converter did not know), with raw HTML shown as text and no javascript: link."""
    page = markdown_to_html("a *b* `c` \\*d\\*\n\n    code <b>\n\n<b>raw</b>\n\n[x](javascript:alert(1)) <javascript:alert(2)>", "t & u")
    assert "<p>a <em>b</em> <code>c</code> *d*</p>" in page and "<pre><code>code &lt;b&gt;\n</code></pre>" in page
    assert "&lt;b&gt;raw&lt;/b&gt;" in page and "<b>" not in page
    assert "href" not in page and "<title>t &amp; u</title>" in page
    dependencies = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["dependencies"]
    assert any(re.match(r"markdown-it-py\b", d) for d in dependencies)


CRAFTED = "&lt;script&gt;steal()&lt;/script&gt; <a href='javascript:alert(1)'>a</a> [b](javascript:alert(2)) <javascript:x> `c` **d** |e\\"


def test_a_crafted_name_shows_as_text_in_the_html(results: tuple[Path, Path], tmp_path: Path) -> None:
    """Entities that would decode to a tag, a raw link, a markdown link, an autolink, code, strong, a
    pipe and a trailing backslash (which would escape the cell's closing pipe) in an object and a
    result name: each shows as its own text, in its own cell."""
    folders, _ = results
    hostile = tmp_path / "hostile"
    for folder, name in (("ball-frameps", CRAFTED), ("ball-robust", "robust")):
        shutil.copytree(folders / folder, hostile / folder)
        data = json.loads((hostile / folder / "result.json").read_text())
        (hostile / folder / "result.json").write_text(json.dumps({**data, "object": CRAFTED, "name": name}))
    report = tmp_path / "r.md"
    assert main(["report", str(hostile), "-o", str(report)]) == 0
    page = report.with_suffix(".html").read_text()
    body = page.split("<body>", 1)[1]
    # the entities stay entities of the text (&amp;lt;), never a tag; no element carries a link
    for forbidden in ("<script", "<a ", 'href="', "<code>", "<strong>d", "&lt;script&gt;steal"):
        assert forbidden not in body, forbidden
    header = re.search(r"<thead>\n<tr>\n(.*?)</tr>", body, flags=re.S)[1]  # type: ignore[index]
    assert [html.unescape(cell) for cell in re.findall(r"<th[^>]*>(.*?)</th>", header)] == ["object", CRAFTED, "robust"]
    row = re.search(r"<tbody>\n<tr>\n(.*?)</tr>", body, flags=re.S)[1]  # type: ignore[index]
    cells = re.findall(r"<td[^>]*>(.*?)</td>", row)
    assert len(cells) == 3 and html.unescape(cells[0]) == CRAFTED
