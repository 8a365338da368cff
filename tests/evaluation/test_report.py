"""``pstoolkit report``: the tables hold every pair with the numbers of its result.json, the figures
exist at their layout's size, the HTML carries the same tables and images, a batch's failed pairs are
listed, and results without ground truth get everything but the errors."""

from __future__ import annotations

import dataclasses
import html
import json
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from helpers.batch import session_captures

import psfmt
from pstoolkit.cli import main
from pstoolkit.evaluation.batchlog import Outcome
from pstoolkit.solve.batch import plan, run_pair, solver_options, write_log

SOLVERS = ["frameps", "eventps"]


@pytest.fixture(scope="module")
def batch_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Result folders of frameps and eventps on three captures (written by the batch's worker
    function, in this process), and a batch log with one failed pair."""
    root = tmp_path_factory.mktemp("report")
    captures = session_captures(tmp_path_factory)
    out = root / "batch"
    pairs = plan(captures, solver_options(SOLVERS, []), out, device="cpu")
    outcomes = [run_pair(pair) for pair in pairs]
    assert all(o.status == "done" for o in outcomes)
    broken = Outcome("broken", "frameps", str(root / "broken.h5"), str(out / "broken-frameps"), "failed", error="broken.h5: not an HDF5 file")
    write_log(out, [*outcomes, broken])
    return out


def _size(path: Path) -> tuple[int, int]:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert image is not None, path
    return image.shape[1], image.shape[0]


def _table(text: str, title: str) -> dict[str, list[str]]:
    """Rows (object → cells) of the markdown table under the heading ``title``."""
    block = text.split(f"## {title}\n\n", 1)[1].split("\n\n", 1)[0].splitlines()
    assert block[0] == "| object | eventps | frameps |"
    return {cells[0]: cells[1:] for cells in ([c.strip() for c in line.strip("|").split("|")] for line in block[2:])}


def test_report_tables_figures_and_html(batch_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    report = tmp_path / "rep" / "summary.md"
    assert main(["report", str(batch_dir), "-o", str(report)]) == 0
    assert capsys.readouterr().out == f"wrote {report}, summary.html and 4 figure(s)\n"
    text = report.read_text()
    results = {(r["object"], r["solver"]): r for r in (json.loads(p.read_text()) for p in batch_dir.glob("*/result.json"))}
    assert len(results) == 6
    tables = {
        "mae_deg": ("Mean angular error (degrees)", "{:.2f}"),
        "mae_solved_deg": ("Mean angular error of the solved pixels (degrees)", "{:.2f}"),
        "median_deg": ("Median angular error (degrees)", "{:.2f}"),
        "coverage": ("Coverage (% of mask pixels solved)", "{:.1f} %"),
        "below_11_25": ("Pixels under 11.25° (% of the mask)", "{:.1f} %"),
        "below_22_5": ("Pixels under 22.5° (% of the mask)", "{:.1f} %"),
        "below_30": ("Pixels under 30° (% of the mask)", "{:.1f} %"),
        "data_rate": ("Data rate (% of 24 RGB frames)", "{:.1f} %"),
    }
    for key, (title, fmt) in tables.items():
        table = _table(text, title)
        assert sorted(table) == ["**average**", "ball", "blobs", "relief"]
        for (obj, solver), result in results.items():
            value = result[key] * (1 if key.endswith("_deg") else 100)
            assert table[obj][["eventps", "frameps"].index(solver)] == fmt.format(value)
    mae = _table(text, "Mean angular error (degrees)")
    # eventps gives every pixel a normal
    assert _table(text, "Coverage (% of mask pixels solved)")["**average**"][0] == "100.0 %"
    assert mae["ball"][1] != "–" and float(mae["ball"][1]) < 10.0
    plot = report.parent / "summary-mae-vs-data-rate.png"
    maps = [report.parent / f"summary-maps-{i:03d}-{obj}.png" for i, obj in enumerate(("ball", "blobs", "relief"))]
    assert sorted(report.parent.iterdir()) == sorted([report, report.with_suffix(".html"), plot, *maps])
    assert _size(plot) == (640, 480)
    assert all(_size(path) == (2 * 240, 2 * 260) for path in maps)  # two solvers side by side: normals over errors
    assert f"![Mean angular error against data rate]({plot.name})" in text
    assert all(f"![{obj}]({path.name})" in text for obj, path in zip(("ball", "blobs", "relief"), maps))
    assert text.rstrip().endswith("## Failed pairs\n\n- broken × frameps: broken.h5: not an HDF5 file")
    page = report.with_suffix(".html").read_text()
    assert page.count("<table>") == 9 and page.count("<img ") == 4
    assert all(f'<img src="{path.name}"' in page for path in (plot, *maps))
    for obj, cells in mae.items():
        row = re.sub(r"\*\*(.+)\*\*", r"<strong>\1</strong>", obj)
        # markdown-it writes one cell per line
        assert "\n".join([f'<td style="text-align:left">{row}</td>', *(f'<td style="text-align:right">{c}</td>' for c in cells)]) in page
    assert "<li>broken × frameps: broken.h5: not an HDF5 file</li>" in page


def test_results_without_ground_truth_report_everything_but_the_errors(batch_dir: Path, tmp_path: Path) -> None:
    blind = tmp_path / "blind.h5"
    capture = psfmt.load(json.loads((batch_dir / "ball-frameps" / "result.json").read_text())["capture"])
    psfmt.write(dataclasses.replace(capture, ground_truth=None), blind)
    (pair,) = plan([blind], solver_options(["frameps"], []), tmp_path / "batch", device="cpu")
    assert run_pair(pair).status == "done"
    report = tmp_path / "blind.md"
    assert main(["report", str(tmp_path / "batch"), "-o", str(report)]) == 0
    text = report.read_text()
    assert "Mean angular error" not in text and "Median" not in text and "## Failed pairs" not in text
    assert "Coverage" not in text and "Pixels under" not in text
    assert "No result has ground truth: the error tables, the plot and the error maps are left out." in text
    assert "| blind | 12.5 % |" in text and "## Normal maps\n\n![blind](blind-maps-000-blind.png)" in text
    assert sorted(p.name for p in tmp_path.iterdir() if p.suffix == ".png") == ["blind-maps-000-blind.png"]
    assert _size(tmp_path / "blind-maps-000-blind.png") == (240, 260)  # one normal map, no error row


def test_bad_input_is_one_line_exit_2(batch_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    capture = json.loads((batch_dir / "ball-frameps" / "result.json").read_text())["capture"]
    cases = {
        (str(batch_dir), "-o", str(tmp_path / "r.html")): (
            f"-o {tmp_path / 'r.html'}: name the markdown file of the report (….md); the HTML and the figures go beside it"
        ),
        (capture, "-o", str(tmp_path / "r.md")): f"{capture}: not a folder (the report reads result folders written by `pstoolkit run` or `pstoolkit batch`)",
        (str(tmp_path), "-o", str(tmp_path / "r.md")): f"{tmp_path}: no result.json in this folder or its subfolders",
    }
    for args, message in cases.items():
        assert main(["report", *args]) == 2
        assert capsys.readouterr().err == f"pstoolkit: error: {message}\n"


HOSTILE_OBJECT = "<img src=x onerror=alert(1)>|ball\n# injected"
HOSTILE_SOLVER = "ev|ps<script>alert(1)</script>"


def _renamed(source: Path, target: Path, obj: str, name: str) -> None:
    shutil.copytree(source, target)
    data = json.loads((target / "result.json").read_text())
    (target / "result.json").write_text(json.dumps({**data, "object": obj, "name": name}))


def test_names_from_files_are_escaped_for_markdown_and_html(batch_dir: Path, tmp_path: Path) -> None:
    """Issue 19, item 10: HTML, a newline (a heading) and a pipe (a cell) in names from result files
    and in a batch log's error show as text in the markdown and in the HTML page."""
    hostile = tmp_path / "hostile"
    _renamed(batch_dir / "ball-frameps", hostile / "a", HOSTILE_OBJECT, "frameps")
    _renamed(batch_dir / "ball-eventps", hostile / "b", HOSTILE_OBJECT, HOSTILE_SOLVER)
    failed = Outcome("o|x", "frameps", "c.h5", str(hostile / "c"), "failed", error="<script>steal()</script>\n## fake")
    write_log(hostile, [failed])
    report = tmp_path / "r.md"
    assert main(["report", str(hostile), "-o", str(report)]) == 0
    text, page = report.read_text(), report.with_suffix(".html").read_text()
    for document in (text, page):
        assert "<img src=x" not in document and "<script" not in document
        assert "\n# injected" not in document and "\n## fake" not in document
    table = text.split("## Mean angular error (degrees)\n\n", 1)[1].split("\n\n", 1)[0].splitlines()
    cells = [re.split(r"(?<!\\)\|", line.strip()[1:-1]) for line in table]
    assert [len(row) for row in cells] == [3] * len(cells)  # object | ev|ps… | frameps, in every row
    escaped_object = html.escape(HOSTILE_OBJECT.replace("\n", " "), quote=False)
    assert f"<td style=\"text-align:left\">{escaped_object}</td>" in page
    assert f"<th style=\"text-align:right\">{html.escape(HOSTILE_SOLVER, quote=False)}</th>" in page
    assert f"<li>o|x × frameps: {html.escape('<script>steal()</script> ## fake', quote=False)}</li>" in page


def test_a_failed_report_leaves_the_old_one_whole(batch_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 19, item 12: a report that fails (here on an error.npy of Python objects, which is never
    unpickled) replaces none of the files of the report already at its path."""
    report = tmp_path / "out" / "r.md"
    assert main(["report", str(batch_dir), "-o", str(report)]) == 0
    before = {p.name: p.read_bytes() for p in report.parent.iterdir()}
    broken = tmp_path / "broken"
    for folder in ("ball-frameps", "blobs-frameps"):
        shutil.copytree(batch_dir / folder, broken / folder)
    bad = broken / "blobs-frameps" / "error.npy"
    np.save(bad, np.array([{"x": 1}], dtype=object), allow_pickle=True)
    capsys.readouterr()
    assert main(["report", str(broken), "-o", str(report)]) == 2
    assert capsys.readouterr().err == (
        f"pstoolkit: error: {bad}: expected an array of numbers, got object\n"
    )
    assert {p.name: p.read_bytes() for p in report.parent.iterdir()} == before
