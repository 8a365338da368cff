"""``pstoolkit eval``: tables over result folders, folders of them and captures with stored results."""

from __future__ import annotations

import csv
import dataclasses
import io
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from helpers.solvers import lsq_plugin, simulate_sphere

import psfmt
from pstoolkit.cli import main
from pstoolkit.evaluation.metrics import angular_error_deg
from pstoolkit.evaluation.scoring import Record, collect, markdown_table


@dataclass(frozen=True)
class Runs:
    """``out/`` holds sphere-lsq, sphere-lsq-hi and nogt-lsq; ``ball.h5`` holds a stored lsq result."""

    root: Path
    out: Path
    sphere: Path
    ball: Path


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> Runs:
    root = tmp_path_factory.mktemp("eval")
    with pytest.MonkeyPatch.context() as monkeypatch, lsq_plugin(monkeypatch, root):
        sphere = simulate_sphere(root / "sphere.h5")
        ball = simulate_sphere(root / "ball.h5", "--elevation-deg", "60")
        with psfmt.read(sphere) as capture:
            psfmt.write(dataclasses.replace(capture, ground_truth=None), root / "nogt.h5")
        out = root / "out"
        base = ["run", "--solver", "lsq", "--device", "cpu"]
        assert main([*base, str(sphere), "-o", str(out / "sphere-lsq")]) == 0
        assert main([*base, str(sphere), "-o", str(out / "sphere-lsq-hi"), "--name", "lsq-hi", "--set", "threshold=0.5"]) == 0
        assert main([*base, str(root / "nogt.h5"), "-o", str(out / "nogt-lsq")]) == 0
        assert main([*base, str(ball), "-o", str(root / "ball-lsq"), "--store"]) == 0
    return Runs(root, out, sphere, ball)


def folder(path: Path) -> dict:
    return json.loads((path / "result.json").read_text())


def test_capture_results_are_scored_against_its_ground_truth(runs: Runs) -> None:
    (record,) = collect([runs.ball])
    with psfmt.read(runs.ball) as capture:
        stored = capture.results["lsq"]
        errors = angular_error_deg(stored.maps["normal"], capture.ground_truth.normal, capture.ground_truth.mask)
        rate = psfmt.data_rate(capture).rate
        mask = ~np.isnan(errors)
        solved = mask & np.any(stored.maps["normal"] != 0, axis=-1)
    inside = errors[mask]
    assert record == Record(
        object="ball",
        solver="lsq",
        mae_deg=float(inside.mean()),
        mae_solved_deg=float(errors[solved].mean()),
        median_deg=float(np.median(inside)),
        coverage=float(solved.sum() / mask.sum()),
        below_11_25=float(np.mean(inside < 11.25)),
        below_22_5=float(np.mean(inside < 22.5)),
        below_30=float(np.mean(inside < 30)),
        data_rate=rate,
        seconds=stored.seconds,
        depth_error=None,
        source=str(runs.ball),
    )
    ran = folder(runs.root / "ball-lsq")  # what `run` reported for the same maps
    for metric in ("mae_deg", "mae_solved_deg", "median_deg", "coverage", "below_11_25", "below_22_5", "below_30", "seconds"):
        assert getattr(record, metric) == pytest.approx(ran[metric], abs=1e-9)


def test_markdown_tables_over_folders_and_a_capture(runs: Runs, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["eval", str(runs.out), str(runs.ball)]) == 0
    text = capsys.readouterr().out
    lsq, hi, nogt = folder(runs.out / "sphere-lsq"), folder(runs.out / "sphere-lsq-hi"), folder(runs.out / "nogt-lsq")
    (ball,) = collect([runs.ball])
    assert nogt["mae_deg"] is None and hi["mae_deg"] > lsq["mae_deg"]  # the higher threshold leaves the darkest pixels out: 90° each
    mean = (ball.mae_deg + lsq["mae_deg"]) / 2
    assert text.startswith(
        "### Mean angular error (degrees)\n\n"
        "| object | lsq | lsq-hi |\n"
        "|:--|--:|--:|\n"
        f"| ball | {ball.mae_deg:.2f} | – |\n"
        "| nogt | – | – |\n"
        f"| sphere | {lsq['mae_deg']:.2f} | {hi['mae_deg']:.2f} |\n"
        f"| **average** | {mean:.2f} | {hi['mae_deg']:.2f} |\n\n"
        "### Mean angular error of the solved pixels (degrees)\n\n"
    )
    # the pixels lsq-hi leaves out count 90° in its MAE; the coverage table says how many there are
    assert hi["coverage"] < lsq["coverage"] == 1.0 and hi["mae_solved_deg"] < hi["mae_deg"]
    cover = f"{100 * lsq['coverage']:.1f} % | {100 * hi['coverage']:.1f} %"
    assert (
        "### Coverage (% of mask pixels solved)\n\n"
        "| object | lsq | lsq-hi |\n"
        "|:--|--:|--:|\n"
        f"| ball | {100 * ball.coverage:.1f} % | – |\n"
        "| nogt | – | – |\n"
        f"| sphere | {cover} |\n"
    ) in text
    for key, title in (("below_11_25", "11.25"), ("below_22_5", "22.5"), ("below_30", "30")):
        assert f"### Pixels under {title}° (% of the mask)\n\n" in text
        assert f"| sphere | {100 * lsq[key]:.1f} % | {100 * hi[key]:.1f} % |\n" in text
    assert f"| sphere | {lsq['mae_solved_deg']:.2f} | {hi['mae_solved_deg']:.2f} |\n" in text
    rate = f"{100 * 8 / 24:.1f} %"
    assert (
        "### Data rate (% of 24 RGB frames)\n\n"
        "| object | lsq | lsq-hi |\n"
        "|:--|--:|--:|\n"
        f"| ball | {rate} | – |\n"
        f"| nogt | {rate} | – |\n"
        f"| sphere | {rate} | {rate} |\n"
        f"| **average** | {rate} | {rate} |\n\n"
    ) in text
    seconds = f"| sphere | {lsq['seconds']:.3f} | {hi['seconds']:.3f} |\n"
    assert text.endswith(seconds + f"| **average** | {(ball.seconds + lsq['seconds'] + nogt['seconds']) / 3:.3f} | {hi['seconds']:.3f} |\n")


def test_csv_and_json_agree_with_the_records(runs: Runs, capsys: pytest.CaptureFixture[str]) -> None:
    records = collect([runs.out / "sphere-lsq", runs.out / "nogt-lsq", runs.ball])
    assert main(["eval", str(runs.out / "sphere-lsq"), str(runs.out / "nogt-lsq"), str(runs.ball), "--csv"]) == 0
    rows = list(csv.DictReader(io.StringIO(capsys.readouterr().out)))
    metrics = ["mae_deg", "mae_solved_deg", "median_deg", "coverage", "below_11_25", "below_22_5", "below_30", "data_rate", "seconds"]
    assert [list(row) for row in rows[:1]] == [["object", "solver", *metrics, "depth_error"]]
    # no result here has an integrated surface
    assert all(row["depth_error"] == "" for row in rows)
    assert [(row["object"], row["solver"]) for row in rows] == [("ball", "lsq"), ("nogt", "lsq"), ("sphere", "lsq")]
    assert all(rows[1][key] == "" for key in metrics[:-2])
    for row, record in zip(rows, records, strict=True):
        for key in metrics:
            value = getattr(record, key)
            assert row[key] == ("" if value is None else repr(value))
    assert main(["eval", str(runs.out / "sphere-lsq"), str(runs.out / "nogt-lsq"), str(runs.ball), "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["results"] == [dataclasses.asdict(r) for r in records]
    assert data["average"] == {
        "lsq": {
            **{key: pytest.approx((getattr(records[0], key) + getattr(records[2], key)) / 2) for key in metrics[:-2]},
            "data_rate": pytest.approx(8 / 24),
            "seconds": pytest.approx(sum(r.seconds for r in records) / 3),
            "depth_error": None,
        }
    }


def test_output_file_is_written_instead_of_printed(runs: Runs, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    target = tmp_path / "table.md"
    assert main(["eval", str(runs.out), "-o", str(target)]) == 0
    assert capsys.readouterr().out == f"wrote {target}: 3 result(s)\n"
    assert target.read_text() == "\n\n".join(
        f"### {title}\n\n{markdown_table(collect([runs.out]), metric)}"
        for metric, title in (
            ("mae_deg", "Mean angular error (degrees)"),
            ("mae_solved_deg", "Mean angular error of the solved pixels (degrees)"),
            ("median_deg", "Median angular error (degrees)"),
            ("coverage", "Coverage (% of mask pixels solved)"),
            ("below_11_25", "Pixels under 11.25° (% of the mask)"),
            ("below_22_5", "Pixels under 22.5° (% of the mask)"),
            ("below_30", "Pixels under 30° (% of the mask)"),
            ("data_rate", "Data rate (% of 24 RGB frames)"),
            ("seconds", "Solver time (seconds)"),
        )
    ) + "\n"
    assert [p.name for p in tmp_path.iterdir()] == ["table.md"]


def test_bad_input_is_one_line_exit_2(runs: Runs, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "result.json").write_text("{not json")
    (tmp_path / "empty").mkdir()
    cases = [
        ([str(tmp_path / "missing")], f"{tmp_path / 'missing'}: no such file or folder"),
        ([str(tmp_path / "empty")], f"{tmp_path / 'empty'}: no result.json in this folder or its subfolders"),
        ([str(broken)], f"{broken / 'result.json'}: not valid JSON (Expecting property name enclosed in double quotes at line 1)"),
        (
            [str(runs.sphere)],
            f"{runs.sphere}: the capture holds no stored results (store one with `pstoolkit run --store`)",
        ),
        (
            [str(runs.out), str(runs.out / "sphere-lsq")],
            f"two results for object 'sphere' and solver 'lsq': {runs.out / 'sphere-lsq'} and {runs.out / 'sphere-lsq'} "
            "(give one of them another name with `pstoolkit run --name`)",
        ),
        ([str(runs.out), "--json", "--csv"], "--json and --csv: choose one output format"),
        ([str(runs.out), "-o", str(tmp_path / "no" / "t.md")], f"{tmp_path / 'no' / 't.md'}: folder {tmp_path / 'no'} does not exist"),
    ]
    for args, message in cases:
        assert main(["eval", *args]) == 2
        captured = capsys.readouterr()
        assert (captured.out, captured.err) == ("", f"pstoolkit: error: {message}\n")
