"""The evaluation report of result folders (``pstoolkit report``): markdown and HTML with figures.

The report holds the tables of ``pstoolkit eval`` (object × solver: mean angular error, of the solved
pixels too, median error, coverage, shares under 11.25°/22.5°/30°, data rate, solver time, with
average rows; the depth error where a surface was integrated), a plot of the mean angular error
against the data rate per solver (every object faint, the solver's average bold), and per object one
figure with each solver's normal map (titled with its MAE and coverage) above its error map
(unsolved pixels grey) and its depth thumbnail when a surface was integrated
(``pstoolkit integrate``), plus the pairs a batch failed on (from ``batch.json``).
Without ground truth the error tables, the plot and the error maps are left out. Figures are PNGs
beside the report, named ``<report stem>-…png``, drawn with matplotlib's Agg canvas (no pyplot, so
no global backend state).

Names and error lines come from files: the markdown escapes them (``markup.md``), the HTML page is
made from that markdown and escapes them again for HTML, and the figures show them without
mathtext. The report is written as a unit: every figure and page is made beside its target first,
and only when all are made do they replace the old ones, so a failed report leaves the old one whole.
"""

from __future__ import annotations

import html
import json
import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from psfmt.atomic import check_target, commit, temporary_sibling
from psfmt.text import printable
from pstoolkit.errors import UserError
from pstoolkit.evaluation.markup import ESCAPE, md
from pstoolkit.evaluation.scoring import GROUND_TRUTH_METRICS, METRICS, RESULT_FILE, TITLES, Record, averages, collect, markdown_table
from pstoolkit.io.normalmap import normal_to_rgb, read_normal_npy, read_npy
from pstoolkit.solve.batch import read_failures
from pstoolkit.solve.results import error_to_rgb

DPI = 100
PANEL_PX = (240, 260)
"""Width and height in pixels of one panel of a maps figure (a map and its title)."""
PLOT_PX = (640, 480)
"""Width and height in pixels of the MAE-against-data-rate plot."""


@dataclass(frozen=True)
class ReportFiles:
    """What ``write_report`` wrote: the markdown, the HTML and the PNG figures."""

    markdown: Path
    html: Path
    figures: list[Path]


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]", "_", name)


def _label(name: str) -> str:
    """A name for a figure: one printable line, ``$`` escaped so matplotlib draws no mathtext."""
    return printable(name).replace("$", r"\$")


def _save(fig: Figure, path: Path) -> None:
    # a PNG whatever the name: write_report draws into hidden temporary files
    fig.savefig(path, dpi=DPI, format="png")


def plot_mae_vs_rate(records: list[Record], path: Path) -> None:
    """MAE (degrees) against data rate (% of 24 RGB frames): per solver its objects as faint points
    and its average as a large marker."""
    fig = Figure(figsize=(PLOT_PX[0] / DPI, PLOT_PX[1] / DPI), dpi=DPI, layout="constrained")
    ax = fig.add_subplot()
    mean = averages(records)
    for index, solver in enumerate(sorted(mean)):
        colour = f"C{index % 10}"
        points = [(100 * r.data_rate, r.mae_deg) for r in records if r.solver == solver and r.mae_deg is not None and r.data_rate is not None]
        if not points:
            continue
        x, y = np.array(points).T
        ax.scatter(x, y, s=18, color=colour, alpha=0.35)
        ax.scatter([x.mean()], [y.mean()], s=90, color=colour, edgecolors="black", label=f"{_label(solver)} (average)", zorder=3)
    ax.set_xlabel("data rate (% of 24 RGB frames)")
    ax.set_ylabel("mean angular error (°)")
    ax.set_title("Mean angular error against data rate")
    ax.set_xlim(left=0)
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize="small")
    _save(fig, path)


def _error_map(folder: Path) -> tuple[np.ndarray, float] | None:
    """``error.npy`` of a result folder (a float (H, W) map of degrees, else a UserError) and the top
    of its colour scale, or None without ground truth."""
    path = folder / "error.npy"
    if not path.is_file():
        return None
    error = read_npy(path)
    if error.ndim != 2 or error.dtype.kind != "f":
        raise UserError(f"{path}: expected a float (H, W) error map in degrees, got {error.dtype} {error.shape}")
    data = json.loads((folder / RESULT_FILE).read_text(encoding="utf-8"))
    top = data.get("error_max_deg")
    usable = isinstance(top, (int, float)) and not isinstance(top, bool) and math.isfinite(top) and top > 0
    return error, float(top) if usable else 30.0


def _depth_map(folder: Path) -> np.ndarray | None:
    """``depth.npy`` of a result folder with an integrated surface (a float (H, W) map, else a
    UserError), None without one."""
    path = folder / "depth.npy"
    if not path.is_file():
        return None
    depth = read_npy(path)
    if depth.ndim != 2 or depth.dtype.kind != "f":
        raise UserError(f"{path}: expected a float (H, W) depth map, got {depth.dtype} {depth.shape}")
    return depth


def _depth_image(depth: np.ndarray) -> np.ndarray:
    """Grey (H, W) in [0, 1] of a depth map, nearer brighter, black where it has no depth."""
    inside = np.isfinite(depth)
    if not inside.any():
        return np.zeros(depth.shape)
    low, high = float(depth[inside].min()), float(depth[inside].max())
    grey = (depth - low) / (high - low) * 0.8 + 0.2 if high > low else np.full(depth.shape, 0.6)
    return np.where(inside, grey, 0.0)


def plot_maps(records: list[Record], path: Path) -> None:
    """One object's figure: a column per solver with its normal map (titled with its MAE and coverage)
    above its error map (Turbo, 0 to the folder's error scale, grey where the solver left a pixel
    unsolved: a zero normal) and, where a surface was integrated, its depth (nearer brighter, titled
    with the depth error); no error row when no result has ground truth, no depth row when no result
    has a surface."""
    errors = [_error_map(Path(r.source)) for r in records]
    depths = [_depth_map(Path(r.source)) for r in records]
    has_error, has_depth = any(e is not None for e in errors), any(d is not None for d in depths)
    rows = 1 + has_error + has_depth
    fig = Figure(figsize=(len(records) * PANEL_PX[0] / DPI, rows * PANEL_PX[1] / DPI), dpi=DPI, layout="constrained")
    axes = fig.subplots(rows, len(records), squeeze=False)
    for column, (record, error, depth) in enumerate(zip(records, errors, depths)):
        normal = read_normal_npy(Path(record.source) / "normal.npy")
        score = f"MAE {record.mae_deg:.2f}°" if record.mae_deg is not None else "no ground truth"
        if record.coverage is not None:
            score += f", {100 * record.coverage:.1f} % solved"
        axes[0, column].imshow(normal_to_rgb(normal, bits=8), interpolation="nearest")
        axes[0, column].set_title(f"{_label(record.solver)}\n{score}", fontsize="small")
        if has_error:
            if error is None:
                axes[1, column].text(0.5, 0.5, "no ground truth", ha="center", va="center", transform=axes[1, column].transAxes)
            else:
                solved = np.any(normal != 0, axis=-1)
                axes[1, column].imshow(error_to_rgb(error[0], error[1], solved), interpolation="nearest")
                grey = ", grey: unsolved" if np.any(np.isfinite(error[0]) & ~solved) else ""
                axes[1, column].set_title(f"error 0–{error[1]:g}°{grey}", fontsize="small")
        if has_depth:
            ax = axes[rows - 1, column]
            if depth is None:
                ax.text(0.5, 0.5, "no surface", ha="center", va="center", transform=ax.transAxes)
            else:
                ax.imshow(_depth_image(depth), cmap="gray", vmin=0.0, vmax=1.0, interpolation="nearest")
                detail = "no true depth" if record.depth_error is None else f"RMSE {100 * record.depth_error:.2f} % of range"
                ax.set_title(f"depth, {detail}", fontsize="small")
        for ax in axes[:, column]:
            ax.set_axis_off()
    fig.suptitle(_label(records[0].object))
    _save(fig, path)


def report_markdown(records: list[Record], failures: list[str], plot: str | None, maps: dict[str, str], sources: list[Path]) -> str:
    """The report as markdown; ``plot`` and ``maps`` (object → file) are figure file names beside it.
    Every name, path and error line is escaped (``markup.md``)."""
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
        parts += ["## Mean angular error against data rate", f"![Mean angular error against data rate]({plot})"]
    parts.append("## Normal and error maps" if has_error else "## Normal maps")
    parts += [f"![{md(obj)}]({maps[obj]})" for obj in objects]
    if failures:
        parts += ["## Failed pairs", "\n".join(f"- {md(line)}" for line in failures)]
    return "\n\n".join(parts) + "\n"


_TOKEN = re.compile(ESCAPE.pattern + r"|(&(?:amp|lt|gt|quot|#\d+);)|\*\*(.+?)\*\*|`([^`]+)`")


def _inline(text: str) -> str:
    """HTML of one line of the report's markdown: backslash escapes as their character, entities kept,
    ``**strong**`` and ```code```, everything else HTML-escaped."""
    out, pos = [], 0
    for m in _TOKEN.finditer(text):
        out.append(html.escape(text[pos : m.start()], quote=False))
        if m[1] is not None:
            out.append(html.escape(m[1], quote=False))
        elif m[2] is not None:
            out.append(m[2])
        elif m[3] is not None:
            out.append(f"<strong>{_inline(m[3])}</strong>")
        else:
            out.append(f"<code>{html.escape(m[4], quote=False)}</code>")
        pos = m.end()
    out.append(html.escape(text[pos:], quote=False))
    return "".join(out)


def _literal(text: str) -> str:
    """The text an escaped markdown string shows (for an HTML attribute, which ``html.escape`` quotes)."""
    return html.unescape(ESCAPE.sub(r"\1", text))


def _cells(line: str) -> list[str]:
    """A table row's cells, split at the pipes that are not escaped."""
    return [cell.strip() for cell in re.split(r"(?<!\\)\|", line.strip().removeprefix("|").removesuffix("|"))]


def _html_table(lines: list[str]) -> str:
    align = ["right" if cell.endswith(":") else "left" for cell in _cells(lines[1])]
    head = "".join(f'<th style="text-align:{a}">{_inline(c)}</th>' for c, a in zip(_cells(lines[0]), align))
    body = "".join(
        "<tr>" + "".join(f'<td style="text-align:{a}">{_inline(c)}</td>' for c, a in zip(_cells(line), align)) + "</tr>" for line in lines[2:]
    )
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


_IMAGE = re.compile(r"!\[(.*)\]\((.*)\)")


def markdown_to_html(text: str, title: str) -> str:
    """A standalone HTML page of the markdown ``report_markdown`` writes: headings, paragraphs,
    pipe tables, images and bullet lists (the only constructs it uses)."""
    body = []
    for block in text.strip().split("\n\n"):
        lines = block.splitlines()
        heading = re.match(r"(#{1,6}) (.*)", block)
        image = _IMAGE.fullmatch(block)
        if heading:
            level = len(heading.group(1))
            body.append(f"<h{level}>{_inline(heading.group(2))}</h{level}>")
        elif image:
            alt, src = (html.escape(_literal(part)) for part in image.groups())
            body.append(f'<figure><img src="{src}" alt="{alt}"><figcaption>{alt}</figcaption></figure>')
        elif lines[0].startswith("|"):
            body.append(_html_table(lines))
        elif lines[0].startswith("- "):
            body.append("<ul>" + "".join(f"<li>{_inline(line[2:])}</li>" for line in lines) + "</ul>")
        else:
            body.append(f"<p>{_inline(' '.join(lines))}</p>")
    style = (
        "body{font-family:sans-serif;max-width:72em;margin:2em auto}table{border-collapse:collapse}"
        "td,th{border:1px solid #ccc;padding:.2em .6em}img{max-width:100%}"
    )
    content = "\n".join(body)
    head = f'<head><meta charset="utf-8"><title>{html.escape(title)}</title><style>{style}</style></head>'
    return f'<!DOCTYPE html>\n<html lang="en">\n{head}\n<body>\n{content}\n</body>\n</html>\n'


def write_report(paths: list[Path], out: Path) -> ReportFiles:
    """Report on the result folders under ``paths`` (batch folders or single result folders) into the
    markdown file ``out``, the HTML ``out`` with ``.html`` and PNG figures beside them."""
    if out.suffix.lower() != ".md":
        raise UserError(f"-o {out}: name the markdown file of the report (….md); the HTML and the figures go beside it")
    for path in paths:
        if not path.is_dir():
            raise UserError(f"{path}: not a folder (the report reads result folders written by `pstoolkit run` or `pstoolkit batch`)")
    records = collect(paths)
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
            plot_maps([r for r in records if r.object == obj], stage(out.parent / maps[obj]))
        figures = list(staged)
        text = report_markdown(records, failures, plot, maps, paths)
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
