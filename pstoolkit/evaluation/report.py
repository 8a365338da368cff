"""The evaluation report of result folders (``pstoolkit report``): markdown and HTML with figures.

The report holds the tables of ``pstoolkit eval`` (object × solver: mean angular error, of the solved
pixels too, median error, coverage, shares under 11.25°/22.5°/30°, data rate, solver time, with
average rows; the depth error where a surface was integrated), a plot of the mean angular error
against the data rate (one point per object and solver, each at its own data rate: colour the
solver, marker the object), and per object one figure with each solver's normal map (titled with
its MAE and coverage) above its error map (unsolved pixels grey, a colour bar in degrees) and its
depth thumbnail when a surface was integrated (``pstoolkit integrate``; a colour bar in its
units), plus the pairs a batch failed on (from ``batch.json``).

Ground truth. A result folder holds the error map and the score, not the true normals; those are in
the capture, and the report never opens a path it finds inside a folder (``result.json`` names its
capture: following it would let a folder's files lead the report out of the folders it was given).
So the true normals come only from captures given by the caller (``pstoolkit report
--ground-truth CAPTURE``), matched to results by object (the capture's file stem, as ``pstoolkit
run`` names the object): each figure of such an object starts with a ground-truth column (the true
normal map, and the true depth in mm when a surface row is drawn).

Without ground truth the error tables, the plot and the error maps are left out. Figures are PNGs
beside the report, named ``<report stem>-…png``, drawn with matplotlib's Agg canvas (no pyplot, so
no global backend state).

Names and error lines come from files: the markdown escapes them (``markup.md``), the HTML page is
rendered from that markdown by markdown-it-py (CommonMark with tables) with raw HTML turned off, so
even a string that escaped ``md`` would show as text, and the figures show them without mathtext.
The report is written as a unit: every figure and page is made beside its target first, and only
when all are made do they replace the old ones, so a failed report leaves the old one whole.
"""

from __future__ import annotations

import html
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib
import numpy as np
from markdown_it import MarkdownIt
from matplotlib.axes import Axes
from matplotlib.cm import ScalarMappable
from matplotlib.colors import Colormap, ListedColormap, Normalize
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

import psfmt
from psfmt.atomic import check_target, commit, temporary_sibling
from psfmt.describe import cut
from psfmt.text import printable
from pstoolkit._shared.vectors import solved_pixels
from pstoolkit.errors import UserError
from pstoolkit.evaluation.batchlog import read_failures
from pstoolkit.evaluation.markup import md
from pstoolkit.evaluation.scoring import GROUND_TRUTH_METRICS, METRICS, RESULT_FILE, TITLES, Record, collect, markdown_table
from pstoolkit.io.normalmap import error_to_rgb, normal_to_rgb, read_normal_npy, read_npy
from pstoolkit.io.textdata import read_json_object

DPI = 100
PANEL_PX = (240, 260)
"""Width and height in pixels of one panel of a maps figure (a map and its title)."""
PLOT_PX = (640, 480)
"""Width and height in pixels of the MAE-against-data-rate plot."""
LEGEND_CHARS = 28
"""Longest name in a legend or a panel title (names come from files; the tables give them in full)."""
MARKERS = "osD^vP*Xph<>"
"""Markers of the objects in the MAE-against-data-rate plot; with more objects, all are circles."""
ERROR_CMAP = "turbo"
"""matplotlib's Turbo, the colormap ``error.png`` is drawn with (OpenCV's Turbo), for its colour bar."""
DEPTH_CMAP: Colormap = ListedColormap(matplotlib.colormaps["gray"](np.linspace(0.2, 1.0, 256)), name="depth").with_extremes(bad="black")
"""Depth thumbnails: nearer brighter, from 20 % grey so the farthest point stands out from the black
background (NaN, no depth)."""
DEPTH_UNITS = {"orthographic": "z (frame pixels)", "perspective": "z (relative: up to scale)"}
"""Colour-bar label of a result's depth by its projection (``pstoolkit.surface.base``)."""


@dataclass(frozen=True)
class ReportFiles:
    """What ``write_report`` wrote: the markdown, the HTML and the PNG figures."""

    markdown: Path
    html: Path
    figures: list[Path]


@dataclass(frozen=True)
class Truth:
    """An object's ground truth, from a capture the caller named: ``normal`` (H, W, 3) float unit
    normals (zero outside ``mask``), ``mask`` (H, W) bool, ``depth`` (H, W) float z in mm (NaN
    outside the mask) or None, and ``source``, the capture."""

    normal: np.ndarray
    mask: np.ndarray
    depth: np.ndarray | None
    source: Path


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]", "_", name)


def _label(name: str, limit: int | None = None) -> str:
    """A name for a figure: one printable line (cut to ``limit`` characters with ``…``: a legend of
    long names would squeeze the plot to nothing), ``$`` escaped so matplotlib draws no mathtext."""
    return (printable(name) if limit is None else cut(name, limit)).replace("$", r"\$")


def _save(fig: Figure, path: Path) -> None:
    # a PNG whatever the name: write_report draws into hidden temporary files
    fig.savefig(path, dpi=DPI, format="png")


def read_truths(captures: Sequence[Path], objects: Sequence[str]) -> dict[str, Truth]:
    """The ground truth of each capture in ``captures`` by its object (the file stem). UserError for
    two captures of one object, a capture whose object no result has (``objects``), or one without
    ground-truth normals; FormatError for a file that does not read as a capture."""
    truths: dict[str, Truth] = {}
    for path in captures:
        obj = path.stem
        if obj in truths:
            raise UserError(f"--ground-truth {path}: a second capture of object {obj!r} (the first: {truths[obj].source})")
        if obj not in objects:
            raise UserError(f"--ground-truth {path}: no result is of object {obj!r} (objects: {', '.join(sorted(objects))})")
        with psfmt.read(path) as capture:
            gt = capture.ground_truth
            if gt is None or gt.normal is None:
                raise UserError(f"--ground-truth {path}: the capture holds no ground-truth normals")
            normal = np.asarray(gt.normal, dtype=np.float32)
            mask = np.asarray(gt.mask, dtype=bool) if gt.mask is not None else np.linalg.norm(normal, axis=-1) > 0
            depth = None if gt.depth is None else np.where(mask, np.asarray(gt.depth, dtype=np.float64), np.nan)
        truths[obj] = Truth(np.where(mask[..., None], normal, 0.0), mask, depth, path)
    return truths


def mae_rate_figure(records: list[Record]) -> Figure:
    """MAE (degrees) against data rate (% of 24 RGB frames): one point per object and solver at the
    data rate of that capture (colour: the solver; marker: the object, while there are no more
    objects than ``MARKERS``). No averaged point: captures of different data rates averaged into one
    would sit at a rate no capture has (the tables give the averages)."""
    fig = Figure(figsize=(PLOT_PX[0] / DPI, PLOT_PX[1] / DPI), dpi=DPI, layout="constrained")
    ax = fig.add_subplot()
    points = [r for r in records if r.mae_deg is not None and r.data_rate is not None]
    objects = sorted({r.object for r in points})
    marked = len(objects) <= len(MARKERS)
    solvers: list[Line2D] = []
    for index, solver in enumerate(sorted({r.solver for r in points})):
        colour = f"C{index % 10}"
        for obj in objects:
            mine = [(100 * r.data_rate, r.mae_deg) for r in points if r.solver == solver and r.object == obj]  # type: ignore[operator]
            if mine:
                x, y = np.array(mine).T
                marker = MARKERS[objects.index(obj)] if marked else "o"
                ax.scatter(x, y, s=40, marker=marker, color=colour, edgecolors="black", linewidths=0.5, zorder=3)
        solvers.append(Line2D([], [], color=colour, marker="o", linestyle="", label=_label(solver, LEGEND_CHARS)))
    ax.set_xlabel("data rate (% of 24 RGB frames)")
    ax.set_ylabel("mean angular error (°)")
    ax.set_title("Mean angular error against data rate")
    ax.set_xlim(left=0)
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    # the legends go beside the axes: inside, they would hide the points in their corner
    fig.legend(handles=solvers, title="solver", loc="outside right upper", fontsize="small")
    if marked and objects:
        shapes = [Line2D([], [], color="grey", marker=MARKERS[i], linestyle="", label=_label(obj, LEGEND_CHARS)) for i, obj in enumerate(objects)]
        fig.legend(handles=shapes, title="object", loc="outside right lower", fontsize="small")
    return fig


def plot_mae_vs_rate(records: list[Record], path: Path) -> None:
    """Write ``mae_rate_figure`` as a PNG at ``path``."""
    _save(mae_rate_figure(records), path)


def _summary(folder: Path) -> dict[str, Any]:
    """A result folder's ``result.json`` (checked to be an object when the records were collected)."""
    return read_json_object(folder / RESULT_FILE)


def _float_map(path: Path, what: str) -> np.ndarray | None:
    """The float (H, W) map at ``path`` (else a UserError naming ``what`` it should be), None when the
    file does not exist."""
    if not path.is_file():
        return None
    values = read_npy(path)
    if values.ndim != 2 or values.dtype.kind != "f":
        raise UserError(f"{path}: expected a float (H, W) {what}, got {values.dtype} {values.shape}")
    return values


def _error_map(folder: Path) -> tuple[np.ndarray, float] | None:
    """``error.npy`` of a result folder (a float (H, W) map of degrees, else a UserError) and the top
    of its colour scale, or None without ground truth."""
    error = _float_map(folder / "error.npy", "error map in degrees")
    if error is None:
        return None
    top = _summary(folder).get("error_max_deg")
    usable = isinstance(top, (int, float)) and not isinstance(top, bool) and math.isfinite(top) and top > 0
    return error, float(top) if usable else 30.0


def _depth_map(folder: Path) -> np.ndarray | None:
    """``depth.npy`` of a result folder with an integrated surface (a float (H, W) map, else a
    UserError), None without one."""
    return _float_map(folder / "depth.npy", "depth map")


def _depth_units(folder: Path) -> str:
    """The colour-bar label of a folder's depth: its projection's units (``DEPTH_UNITS``)."""
    surface = _summary(folder).get("surface")
    projection = surface.get("projection") if isinstance(surface, dict) else None
    return DEPTH_UNITS.get(projection, "z") if isinstance(projection, str) else "z"


def _draw_depth(fig: Figure, ax: Axes, depth: np.ndarray, units: str) -> None:
    """A depth map, nearer brighter (``DEPTH_CMAP``), black where it has no depth, with a colour bar
    of z in ``units``."""
    inside = np.isfinite(depth)
    low, high = (float(depth[inside].min()), float(depth[inside].max())) if inside.any() else (0.0, 1.0)
    if high <= low:  # a flat surface: one grey, a bar around its level
        low, high = low - 0.5, high + 0.5
    image = ax.imshow(np.where(inside, depth, np.nan), cmap=DEPTH_CMAP, norm=Normalize(low, high), interpolation="nearest")
    bar = fig.colorbar(image, ax=ax, fraction=0.046, pad=0.03)
    bar.set_label(units, fontsize="x-small")
    bar.ax.tick_params(labelsize="x-small")


def _draw_error(fig: Figure, ax: Axes, error: np.ndarray, top: float, solved: np.ndarray) -> None:
    """An error map as ``error.png`` draws it (Turbo 0…``top``°, black outside the mask, grey where
    unsolved) with a colour bar in degrees, open at the top (larger errors saturate)."""
    ax.imshow(error_to_rgb(error, top, solved), interpolation="nearest")
    scale = ScalarMappable(norm=Normalize(0.0, top), cmap=ERROR_CMAP)
    bar = fig.colorbar(scale, ax=ax, fraction=0.046, pad=0.03, extend="max")
    bar.set_label("angular error (°)", fontsize="x-small")
    bar.ax.tick_params(labelsize="x-small")


def _check_size(truth: Truth, normal: np.ndarray, folder: Path) -> None:
    if truth.normal.shape != normal.shape:
        raise UserError(
            f"--ground-truth {truth.source}: its normals are {truth.normal.shape[0]}×{truth.normal.shape[1]}, the result in {folder} "
            f"{normal.shape[0]}×{normal.shape[1]} (not the capture of this result?)"
        )


def maps_figure(records: list[Record], truth: Truth | None = None) -> Figure:
    """One object's figure: with ``truth``, first a ground-truth column (the true normals, and the
    true depth in mm when there is a depth row); then a column per solver with its normal map
    (titled with its MAE and coverage) above its error map (Turbo, 0 to the folder's error scale,
    grey where the solver left a pixel unsolved: a zero normal; a colour bar in degrees) and, where a
    surface was integrated, its depth (nearer brighter, titled with the depth error, a colour bar in
    the surface's units); no error row when no result has ground truth, no depth row when no result
    has a surface. UserError when ``truth`` is not the size of a result's normals."""
    errors = [_error_map(Path(r.source)) for r in records]
    depths = [_depth_map(Path(r.source)) for r in records]
    has_error, has_depth = any(e is not None for e in errors), any(d is not None for d in depths)
    rows, first = 1 + has_error + has_depth, int(truth is not None)
    columns = first + len(records)
    fig = Figure(figsize=(columns * PANEL_PX[0] / DPI, rows * PANEL_PX[1] / DPI), dpi=DPI, layout="constrained")
    axes = fig.subplots(rows, columns, squeeze=False)
    if truth is not None:
        axes[0, 0].imshow(normal_to_rgb(truth.normal, truth.mask, bits=8), interpolation="nearest")
        axes[0, 0].set_title("ground truth\n(normals)", fontsize="small")
        if has_depth:
            ax = axes[rows - 1, 0]
            if truth.depth is None:
                ax.text(0.5, 0.5, "no true depth", ha="center", va="center", transform=ax.transAxes)
            else:
                _draw_depth(fig, ax, truth.depth, "true z (mm)")
                ax.set_title("true depth", fontsize="small")
    for index, (record, error, depth) in enumerate(zip(records, errors, depths)):
        column = first + index
        normal = read_normal_npy(Path(record.source) / "normal.npy")
        if truth is not None:
            _check_size(truth, normal, Path(record.source))
        score = f"MAE {record.mae_deg:.2f}°" if record.mae_deg is not None else "no ground truth"
        if record.coverage is not None:
            score += f", {100 * record.coverage:.1f} % solved"
        axes[0, column].imshow(normal_to_rgb(normal, bits=8), interpolation="nearest")
        axes[0, column].set_title(f"{_label(record.solver, LEGEND_CHARS)}\n{score}", fontsize="small")
        if has_error:
            if error is None:
                axes[1, column].text(0.5, 0.5, "no ground truth", ha="center", va="center", transform=axes[1, column].transAxes)
            else:
                solved = solved_pixels(normal)
                _draw_error(fig, axes[1, column], error[0], error[1], solved)
                grey = ", grey: unsolved" if np.any(np.isfinite(error[0]) & ~solved) else ""
                axes[1, column].set_title(f"error 0–{error[1]:g}°{grey}", fontsize="small")
        if has_depth:
            ax = axes[rows - 1, column]
            if depth is None:
                ax.text(0.5, 0.5, "no surface", ha="center", va="center", transform=ax.transAxes)
            else:
                _draw_depth(fig, ax, depth, _depth_units(Path(record.source)))
                detail = "no true depth" if record.depth_error is None else f"RMSE {100 * record.depth_error:.2f} % of range"
                ax.set_title(f"depth, {detail}", fontsize="small")
    for ax in axes.flat:
        ax.set_axis_off()
    fig.suptitle(_label(records[0].object, 8 * LEGEND_CHARS // 3))  # the tables give names in full
    return fig


def plot_maps(records: list[Record], path: Path, truth: Truth | None = None) -> None:
    """Write ``maps_figure`` as a PNG at ``path``."""
    _save(maps_figure(records, truth), path)


def report_markdown(
    records: list[Record], failures: list[str], plot: str | None, maps: dict[str, str], sources: list[Path],
    truths: dict[str, Truth] | None = None,
) -> str:
    """The report as markdown; ``plot`` and ``maps`` (object → file) are figure file names beside it,
    ``truths`` the ground truth given per object. Every name, path and error line is escaped
    (``markup.md``)."""
    objects = sorted({r.object for r in records})
    solvers = sorted({r.solver for r in records})
    has_error = any(r.mae_deg is not None for r in records)
    parts = [
        "# Evaluation report",
        f"{len(records)} results: {len(objects)} objects × {len(solvers)} solvers, from "
        + ", ".join(md(s) for s in sources)
        + ".",
    ]
    if not has_error:
        parts.append("No result has ground truth: the error tables, the plot and the error maps are left out.")
    has_depth = any(r.depth_error is not None for r in records)
    for metric in METRICS:
        if metric in GROUND_TRUTH_METRICS and not has_error or metric == "depth_error" and not has_depth:
            continue
        parts += [f"## {TITLES[metric]}", markdown_table(records, metric)]
    if plot is not None:
        parts += [
            "## Mean angular error against data rate",
            "One point per object and solver, at the data rate of what the solver read of that capture.",
            f"![Mean angular error against data rate]({plot})",
        ]
    parts.append("## Normal and error maps" if has_error else "## Normal maps")
    if truths:
        given = ", ".join(f"{md(obj)} ({md(truth.source)})" for obj, truth in sorted(truths.items()))
        parts.append(f"The first column is the ground truth of the capture given for the object: {given}.")
    parts += [f"![{md(obj)}]({maps[obj]})" for obj in objects]
    if failures:
        parts += ["## Failed pairs", "\n".join(f"- {md(line)}" for line in failures)]
    return "\n\n".join(parts) + "\n"


def markdown_to_html(text: str, title: str) -> str:
    """A standalone HTML page of the markdown ``report_markdown`` writes, rendered by markdown-it-py
    (CommonMark with GFM tables). Raw HTML in the markdown is off: a tag is shown as text, never
    passed through, and markdown-it refuses ``javascript:`` links (names are escaped by ``md`` before
    that; this is the second line of defence)."""
    renderer = MarkdownIt("commonmark", {"html": False}).enable("table")
    style = (
        "body{font-family:sans-serif;max-width:72em;margin:2em auto}table{border-collapse:collapse}"
        "td,th{border:1px solid #ccc;padding:.2em .6em}img{max-width:100%}"
    )
    content = renderer.render(text)
    head = f'<head><meta charset="utf-8"><title>{html.escape(title)}</title><style>{style}</style></head>'
    return f'<!DOCTYPE html>\n<html lang="en">\n{head}\n<body>\n{content}</body>\n</html>\n'


def write_report(paths: list[Path], out: Path, ground_truth: Sequence[Path] = ()) -> ReportFiles:
    """Report on the result folders under ``paths`` (batch folders or single result folders) into the
    markdown file ``out``, the HTML ``out`` with ``.html`` and PNG figures beside them. The captures
    in ``ground_truth`` give their objects' figures a ground-truth column (``read_truths``: matched by
    file stem; UserError for one no result is of, or one without ground-truth normals)."""
    if out.suffix.lower() != ".md":
        raise UserError(f"-o {out}: name the markdown file of the report (….md); the HTML and the figures go beside it")
    for path in paths:
        if not path.is_dir():
            raise UserError(f"{path}: not a folder (the report reads result folders written by `pstoolkit run` or `pstoolkit batch`)")
    records = collect(paths)
    truths = read_truths(list(ground_truth), sorted({r.object for r in records}))
    failures = [f"{f.object} × {f.solver}: {f.error}" for path in paths for f in read_failures(path)]
    out.parent.mkdir(parents=True, exist_ok=True)
    staged: dict[Path, Path] = {}  # target → its finished temporary file

    def stage(target: Path) -> Path:
        staged[target] = temporary_sibling(check_target(target))
        return staged[target]

    try:
        plot = None
        if any(r.mae_deg is not None and r.data_rate is not None for r in records):
            plot = f"{out.stem}-mae-vs-data-rate.png"
            plot_mae_vs_rate(records, stage(out.parent / plot))
        maps = {}
        for index, obj in enumerate(sorted({r.object for r in records})):
            maps[obj] = f"{out.stem}-maps-{index:03d}-{_safe(obj)}.png"
            plot_maps([r for r in records if r.object == obj], stage(out.parent / maps[obj]), truths.get(obj))
        figures = list(staged)
        text = report_markdown(records, failures, plot, maps, paths, truths)
        page = out.with_suffix(".html")
        stage(page).write_text(markdown_to_html(text, f"Evaluation report: {', '.join(str(p) for p in paths)}"), encoding="utf-8")
        stage(out).write_text(text, encoding="utf-8")
        # everything is made: now the new files replace the old ones, the markdown last
        for target in list(staged):
            commit(staged.pop(target), target)
    finally:
        for tmp in staged.values():
            tmp.unlink(missing_ok=True)
    return ReportFiles(out, page, figures)
