"""Scoring normal maps against ground truth, and collecting scored results into tables.

``score`` is what ``pstoolkit run`` reports; ``collect`` gathers ``Record``s from result folders
(``result.json`` written by ``run``), folders of result folders, and captures with stored results
(scored afresh against the capture's ground truth); ``markdown``, ``csv_text`` and ``json_text`` lay
them out with objects as rows and result names (the solver, or ``run --name``) as columns.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

import psfmt
from pstoolkit._shared.vectors import solved_pixels
from pstoolkit.errors import UserError
from pstoolkit.evaluation.markup import md
from pstoolkit.evaluation.metrics import SHARE_KEYS, THRESHOLDS_DEG, angular_error_deg, error_stats
from pstoolkit.io.textdata import read_json_object

MISSING = "–"
RESULT_FILE = "result.json"
METRICS = ("mae_deg", "mae_solved_deg", "median_deg", "coverage", *SHARE_KEYS, "data_rate", "seconds", "depth_error")
TITLES = {
    "mae_deg": "Mean angular error (degrees)",
    "mae_solved_deg": "Mean angular error of the solved pixels (degrees)",
    "median_deg": "Median angular error (degrees)",
    "coverage": "Coverage (% of mask pixels solved)",
    **{key: f"Pixels under {threshold:g}° (% of the mask)" for key, threshold in zip(SHARE_KEYS, THRESHOLDS_DEG)},
    "data_rate": "Data rate (% of 24 RGB frames)",
    "seconds": "Solver time (seconds)",
    "depth_error": "Depth RMSE after scale and offset alignment (% of the true depth range)",
}
PERCENT_METRICS = frozenset({"coverage", *SHARE_KEYS, "data_rate", "depth_error"})
"""Metrics stored as shares 0..1 and shown in percent."""
GROUND_TRUTH_METRICS = frozenset(METRICS) - {"data_rate", "seconds"}
"""Metrics that need ground truth."""
CSV_COLUMNS = ("object", "solver", *METRICS)


@dataclass(frozen=True)
class Score:
    """Angular error of a normal map: ``error_deg`` (H, W) float32 degrees, NaN outside the
    ground-truth mask (90° where the solver left a pixel out), ``solved`` (H, W) the pixels the solver
    estimated (a non-zero normal), and the summary ``stats`` (``metrics.error_stats``)."""

    error_deg: np.ndarray
    solved: np.ndarray
    stats: dict[str, Any]


@dataclass(frozen=True)
class Record:
    """One scored result: ``object`` (capture stem, ``demo`` for the demo capture), ``solver`` (the
    result's name: the solver's, or the one given to ``run --name``), the ``METRICS`` (None where
    unknown: no ground truth, or a result.json written before the metric existed; ``depth_error``
    only for a result folder with an integrated surface, ``pstoolkit.surface.outputs``), and
    ``source``, the folder or capture it was read from."""

    object: str
    solver: str
    mae_deg: float | None
    mae_solved_deg: float | None
    median_deg: float | None
    coverage: float | None
    below_11_25: float | None
    below_22_5: float | None
    below_30: float | None
    data_rate: float | None
    seconds: float | None
    depth_error: float | None
    source: str


def score(normal: np.ndarray, gt: psfmt.GroundTruth | None) -> Score | None:
    """Error of ``normal`` over the ground-truth mask (non-zero ground-truth normals when the capture
    stores no mask); None without ground-truth normals. A pixel the solver left out (zero normal)
    (``solved_pixels``: a zero, tiny or non-finite normal) counts as 90° off and as not solved."""
    if gt is None or gt.normal is None:
        return None
    mask = gt.mask if gt.mask is not None else np.linalg.norm(gt.normal, axis=-1) > 0
    errors = angular_error_deg(normal, gt.normal, mask)
    solved = solved_pixels(normal)
    return Score(errors.astype(np.float32), solved, error_stats(errors, solved))


def _number(data: dict[str, Any], key: str, where: Path) -> float | None:
    value = data.get(key)
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise UserError(f"{where}: {key!r} is {value!r}, expected a number or null")
    return float(value)


def _depth_error(data: dict[str, Any], where: Path) -> float | None:
    """The surface's depth RMSE as a share of the true depth range, None without one."""
    surface = data.get("surface")
    error = surface.get("depth_error") if isinstance(surface, dict) else None
    if surface is not None and not isinstance(surface, dict) or error is not None and not isinstance(error, dict):
        raise UserError(f"{where}: 'surface' is malformed, expected an object with a 'depth_error' object or null")
    return None if error is None else _number(error, "rmse_of_range", where)


def read_result_json(path: Path) -> dict[str, Any]:
    """``result.json`` as a dict ({} when absent). Raises UserError when it is not a JSON object
    within ``pstoolkit.io.textdata``'s bounds (a crafted file may be anything)."""
    if not os.path.lexists(path):
        return {}
    return read_json_object(path)


def read_result_folder(folder: Path) -> Record:
    """The record of a folder written by ``pstoolkit run``."""
    path = folder / RESULT_FILE
    data = read_json_object(path)
    for key in ("object", "name"):
        if not isinstance(data.get(key), str):
            raise UserError(f"{path}: {key!r} is missing or not a string (not a `pstoolkit run` result?)")
    return Record(
        object=data["object"],
        solver=data["name"],
        **{metric: _number(data, metric, path) for metric in METRICS if metric != "depth_error"},
        depth_error=_depth_error(data, path),
        source=str(folder),
    )


def read_capture_results(path: Path) -> list[Record]:
    """Records of the results stored in a capture, each scored against the capture's ground truth."""
    with psfmt.read(path) as capture:
        if not capture.results:
            raise UserError(f"{path}: the capture holds no stored results (store one with `pstoolkit run --store`)")
        whole = psfmt.data_rate(capture).rate
        records = []
        for name, result in sorted(capture.results.items()):
            normal = result.maps.get("normal")
            if normal is None:
                raise UserError(f"{path}: stored result {name!r} has no normal map")
            scored = score(normal, capture.ground_truth)
            stats = scored.stats if scored is not None else {}
            records.append(
                Record(
                    object=path.stem,
                    solver=name,
                    **{metric: stats.get(metric) for metric in GROUND_TRUTH_METRICS},
                    # a result stored without its data rate counts the whole capture
                    data_rate=result.data_rate if result.data_rate is not None else whole,
                    seconds=result.seconds,
                    source=str(path),
                )
            )
    return records


def collect(paths: list[Path]) -> list[Record]:
    """Records from result folders, folders holding result folders (one level down) and captures,
    sorted by object and solver; two records for the same object and solver are a UserError."""
    records: list[Record] = []
    for path in paths:
        if path.is_dir():
            folders = [path] if (path / RESULT_FILE).is_file() else sorted(p for p in path.iterdir() if (p / RESULT_FILE).is_file())
            if not folders:
                raise UserError(f"{path}: no {RESULT_FILE} in this folder or its subfolders")
            records += [read_result_folder(folder) for folder in folders]
        elif path.is_file():
            records += read_capture_results(path)
        else:
            raise UserError(f"{path}: no such file or folder")
    seen: dict[tuple[str, str], str] = {}
    for record in records:
        key = (record.object, record.solver)
        if key in seen:
            raise UserError(
                f"two results for object {record.object!r} and solver {record.solver!r}: {seen[key]} and {record.source} "
                "(give one of them another name with `pstoolkit run --name`)"
            )
        seen[key] = record.source
    return sorted(records, key=lambda r: (r.object, r.solver))


def averages(records: list[Record]) -> dict[str, dict[str, float | None]]:
    """Per solver, the mean of each metric over the objects that have a value for it (None if none)."""
    out: dict[str, dict[str, float | None]] = {}
    for solver in sorted({r.solver for r in records}):
        mine = [r for r in records if r.solver == solver]
        out[solver] = {}
        for metric in METRICS:
            values = [getattr(r, metric) for r in mine if getattr(r, metric) is not None]
            out[solver][metric] = float(np.mean(values)) if values else None
    return out


def format_value(metric: str, value: float | None) -> str:
    """A table cell: degrees to 2 decimals, seconds to 3, shares (``PERCENT_METRICS``) in percent to 1,
    ``–`` when unknown."""
    if value is None:
        return MISSING
    if metric in PERCENT_METRICS:
        return f"{100 * value:.1f} %"
    return f"{value:.3f}" if metric == "seconds" else f"{value:.2f}"


def markdown_table(records: list[Record], metric: str) -> str:
    """One metric as a markdown table: a row per object, a column per solver, and an average row
    (each column averaged over the objects that have a value). Names are escaped (``markup.md``): a
    ``|`` or newline in one cannot move a value into another column or row."""
    solvers = sorted({r.solver for r in records})
    cells = {(r.object, r.solver): getattr(r, metric) for r in records}
    lines = ["| object | " + " | ".join(map(md, solvers)) + " |", "|:--" + "|--:" * len(solvers) + "|"]
    for obj in sorted({r.object for r in records}):
        lines.append(f"| {md(obj)} | " + " | ".join(format_value(metric, cells.get((obj, s))) for s in solvers) + " |")
    mean = averages(records)
    lines.append("| **average** | " + " | ".join(format_value(metric, mean[s][metric]) for s in solvers) + " |")
    return "\n".join(lines)


def markdown(records: list[Record]) -> str:
    """A titled markdown table for each of the ``METRICS``: MAE (all pixels, solved pixels), median
    error, coverage, the shares under 11.25°, 22.5° and 30°, data rate and solver time."""
    shown = [m for m in METRICS if m != "depth_error" or any(r.depth_error is not None for r in records)]
    return "\n\n".join(f"### {TITLES[metric]}\n\n{markdown_table(records, metric)}" for metric in shown) + "\n"


def csv_text(records: list[Record]) -> str:
    """Long format, one row per result: object, solver and the ``METRICS`` (empty where unknown)."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(CSV_COLUMNS)
    for record in records:
        writer.writerow(["" if (v := getattr(record, column)) is None else v for column in CSV_COLUMNS])
    return buffer.getvalue()


def json_text(records: list[Record]) -> str:
    """``{"results": [record …], "average": {solver: {metric: value}}}``, null where unknown."""
    return json.dumps({"results": [asdict(r) for r in records], "average": averages(records)}, indent=2) + "\n"
