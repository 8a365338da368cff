"""One result folder, as ``pstoolkit run`` and ``pstoolkit batch`` write it: ``solve_capture`` runs a
solver on a capture file and scores it, ``result_summary`` builds ``result.json``, and
``write_result_folder`` writes the normal map, the solver's further maps, the error map and, last,
``result.json``, so a folder holding ``result.json`` holds every file it lists.

Image maps — grey (H, W) or RGB (H, W, 3) at the normal map's size — become 16-bit PNGs with
pixel = round(value / scale · 65535), clipped to [0, 65535], and 0 outside the mask, so
value = pixel / 65535 · scale. The scale is 1 for a grey map whose values all lie in [0, 1]
(roughness, metallic: the PNG reads absolutely), else the 99th percentile of the map's finite values
inside the mask — a robust maximum, so a few specular outliers do not darken the whole image. Every
map is also written as ``<name>.npy`` (float maps as float32); a map that is not an image, such as a
per-frame ``normal_sequence`` (N, H, W, 3), only as ``.npy``.

``error.png`` shows the angular error from 0 to ``error_max_deg`` degrees through OpenCV's Turbo
colormap (dark blue at 0°, through cyan, green and yellow, to dark red at ``error_max_deg`` and above),
8-bit RGB, black outside the ground-truth mask and neutral grey (``UNSOLVED_RGB``) where the solver
left a pixel unsolved: its 90° counts in ``mae_deg`` (and ``error.npy``) but is not an error the
solver made, so it is not drawn as one.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

import psfmt
from psfmt.atomic import check_target
from pstoolkit._shared.progress import Progress, no_progress
from pstoolkit.errors import UserError
from pstoolkit.evaluation.metrics import SHARE_KEYS
from pstoolkit.evaluation.scoring import RESULT_FILE, Score, score
from pstoolkit.io.checksum import file_sha256
from pstoolkit.io.folders import atomic_folder
from pstoolkit.io.normalmap import error_to_rgb, write_normal_npy, write_normal_png, write_npy, write_png
from pstoolkit.io.textdata import summary_json
from pstoolkit.plugin.registry import Entry, PluginError
from pstoolkit.solve.base import input_data_rate, run_solver
from pstoolkit.version import __version__

ROBUST_PERCENTILE = 99.0
PNG_TOP = 65535
RESERVED_MAPS = frozenset({"normal", "mask", "error"})
"""Names ``run`` uses itself (``normal.png``, the stored mask, ``error.png``), not open to solver maps."""
_MAP_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_-]*")


@dataclass
class MapOutput:
    """One solver map ready to write: ``array`` for ``<name>.npy``; ``image`` (uint16 grey or RGB)
    for ``<name>.png`` with its ``scale`` (value = pixel / 65535 · scale), both None when the map is
    not an image."""

    name: str
    array: np.ndarray
    image: np.ndarray | None = None
    scale: float | None = None

    def files(self) -> dict[str, object]:
        """The entry for result.json: the file names and the PNG scale."""
        entry: dict[str, object] = {"npy": f"{self.name}.npy", "shape": list(self.array.shape)}
        if self.image is not None:
            entry["png"] = f"{self.name}.png"
            entry["scale"] = self.scale
        return entry


def map_scale(values: np.ndarray, mask: np.ndarray) -> float:
    """1 for a grey map within [0, 1]; else the robust maximum of the finite values inside ``mask``
    (1 when there are none or it is not positive)."""
    inside = values[mask]
    inside = inside[np.isfinite(inside)]
    if inside.size == 0:
        return 1.0
    if values.ndim == 2 and inside.min() >= 0.0 and inside.max() <= 1.0:
        return 1.0
    top = float(np.percentile(inside, ROBUST_PERCENTILE))
    return top if top > 0.0 else 1.0


def encode_map(values: np.ndarray, mask: np.ndarray, scale: float) -> np.ndarray:
    """uint16 pixels round(value / scale · 65535), clipped; 0 outside ``mask`` and where not finite."""
    scaled = np.nan_to_num(values / scale * PNG_TOP, nan=0.0, posinf=PNG_TOP, neginf=0.0)
    image = np.clip(np.floor(scaled + 0.5), 0, PNG_TOP).astype(np.uint16)
    image[~mask] = 0
    return image


def prepare_maps(maps: dict[str, np.ndarray], mask: np.ndarray, blame: str) -> list[MapOutput]:
    """Check and encode a solver's ``maps`` against its (H, W) ``mask``; ``blame`` names the plugin and
    solver in the PluginError a malformed map raises."""
    outputs = []
    for name, value in maps.items():
        if not isinstance(name, str) or not _MAP_NAME.fullmatch(name) or name in RESERVED_MAPS:
            raise PluginError(
                f"{blame} returned a map named {name!r}: names are letters, digits, '_' and '-', "
                f"not {', '.join(sorted(RESERVED_MAPS))}"
            )
        array = np.asarray(value)
        if array.dtype.kind not in "biuf":
            raise PluginError(f"{blame} returned map {name!r} of dtype {array.dtype}, expected numbers")
        if array.dtype.kind == "f":
            array = array.astype(np.float32)
        image_like = array.shape[:2] == mask.shape and (array.ndim == 2 or (array.ndim == 3 and array.shape[2] in (1, 3)))
        if not image_like:
            outputs.append(MapOutput(name, array))
            continue
        values = array[..., 0] if array.ndim == 3 and array.shape[2] == 1 else array
        values = values.astype(np.float64)
        scale = map_scale(values, mask)
        outputs.append(MapOutput(name, array, encode_map(values, mask, scale), scale))
    return outputs


def write_maps(folder: Path, outputs: list[MapOutput]) -> None:
    """Write each prepared map as ``<name>.npy`` and, for images, ``<name>.png`` into ``folder``."""
    for output in outputs:
        write_npy(folder / f"{output.name}.npy", output.array)
        if output.image is not None:
            write_png(folder / f"{output.name}.png", output.image)


MAX_ERROR_DEG = 180.0
"""The largest angle between two directions: the top of an error scale is at most this."""


def check_error_max(value: float, where: str) -> float:
    """``value`` (degrees, the top of ``error.png``'s scale) when it lies in (0, 180]; else a
    UserError naming ``where`` (``--error-max``, ``error_max_deg``). Infinity would put every error
    at the bottom of the scale and write ``Infinity`` into result.json, which is not JSON."""
    if not 0.0 < value <= MAX_ERROR_DEG:  # NaN fails too
        raise UserError(f"{where} {value:g}: expected a number of degrees above 0 and at most {MAX_ERROR_DEG:g}")
    return float(value)


def write_error_map(folder: Path, scored: Score, error_max_deg: float) -> None:
    """``error.npy`` (float32 degrees, NaN outside the mask, 90 where unsolved) and ``error.png``
    (Turbo, grey where unsolved: see the module)."""
    write_npy(folder / "error.npy", scored.error_deg.astype(np.float32))
    write_png(folder / "error.png", error_to_rgb(scored.error_deg, error_max_deg, scored.solved))


@dataclass
class SolvedCapture:
    """A solver's result on one capture, ready to write: ``normal`` (H, W, 3) float32, zero outside
    ``mask``; the prepared further ``maps``; the score against ground truth (None without);
    solver ``seconds``; the ``data_rate`` of what the solver read; the capture's ``kind``."""

    normal: np.ndarray
    mask: np.ndarray
    maps: list[MapOutput]
    scored: Score | None
    seconds: float
    data_rate: float
    capture_kind: str
    diagnostics: dict[str, Any]


def solve_capture(
    entry: Entry, capture: Path, options: dict[str, Any], *, device: str, scheduler: str | None = None,
    workers: int | None = None, progress: Progress = no_progress
) -> SolvedCapture:
    """Read ``capture`` (verified), run the registered solver ``entry`` on it (a tiled solver's tiles
    on ``scheduler`` or a local cluster of ``workers``, ``run_solver``) and score the result."""
    with psfmt.read(capture, verify=True) as data:
        result, seconds = run_solver(entry, data, options, device=device, scheduler=scheduler, workers=workers, progress=progress)
        normal = np.where(result.mask[..., None], result.normal, np.float32(0.0))
        scored = score(normal, data.ground_truth)
        rate = input_data_rate(entry, data, result)
        kind = data.kind
    maps = prepare_maps(result.maps, result.mask, f"plugin {entry.plugin!r}: solver {entry.name!r}")
    return SolvedCapture(normal, result.mask, maps, scored, seconds, rate, kind, result.diagnostics)


def result_summary(
    solved: SolvedCapture,
    *,
    entry: Entry,
    name: str,
    obj: str,
    capture: Path,
    device: str,
    options: dict[str, Any],
    error_max_deg: float,
    stored: bool = False,
) -> dict[str, Any]:
    """The content of ``result.json``: what ran on what, the error statistics and the coverage, the data
    rate, the options and the files of the further maps — and what a repeated run needs
    (``pstoolkit run --config result.json``): the solver, the options as resolved
    (``Solver.resolve_options``), the capture's absolute path and the SHA-256 of the file as it is
    now (``capture_sha256``: call this after anything that writes to the capture, such as ``--store``)
    and the toolkit's version.

    Parameters
    ----------
    solved
        The solved and scored capture (``solve_capture``).
    entry
        The registered solver that ran (its name and plugin are recorded).
    name
        The result's name.
    obj
        The object's name (the capture's stem, or "demo").
    capture
        The capture file.
    device
        The torch device the solver ran on.
    options
        The solver's options as the run used them: parsed and resolved (``solve.base.resolve_options``).
    error_max_deg
        Angular error at the top of ``error.png``'s colour scale, degrees (recorded as None without
        ground truth).
    stored
        Whether the result is also stored in the capture under ``name``.

    Returns
    -------
    dict
        JSON-ready apart from numpy values (``summary_json``); the error statistics in degrees
        (``metrics.error_stats``) are None without ground truth.
    """
    stats = solved.scored.stats if solved.scored is not None else {}
    return {
        "name": name,
        "solver": entry.name,
        "plugin": entry.plugin,
        "object": obj,
        "capture": os.path.abspath(capture),
        "capture_sha256": file_sha256(capture),
        "capture_kind": solved.capture_kind,
        "size": list(solved.normal.shape[:2]),
        "seconds": solved.seconds,
        **{key: stats.get(key) for key in ("mae_deg", "mae_solved_deg", "median_deg", "coverage", *SHARE_KEYS, "n_pixels")},
        "data_rate": solved.data_rate,
        "device": device,
        "options": options,
        "maps": {output.name: output.files() for output in solved.maps},
        "error_max_deg": error_max_deg if solved.scored is not None else None,
        "stored": name if stored else None,
        "pstoolkit_version": __version__,
        "diagnostics": solved.diagnostics,
    }


def check_result_folder(folder: Path, inputs: Sequence[Path] = ()) -> None:
    """UserError unless ``folder`` may be replaced by a result folder (``result_folder``): it does
    not exist, or it is an empty folder or one holding ``result.json`` (an earlier result). Anything
    else — a file, a folder of other files, a link, a folder holding one of ``inputs`` (the capture)
    — is refused rather than deleted (``psfmt.atomic.check_target``). Check before solving, so a long
    run does not end in this error."""
    if folder.is_symlink() or folder.exists() and folder.is_dir():
        check_target(folder, inputs, folder=True)
    if not folder.exists():
        return
    if not folder.is_dir():
        raise UserError(f"{folder}: exists and is not a folder; choose another output folder (-o DIR)")
    if not (folder / RESULT_FILE).is_file() and any(folder.iterdir()):
        raise UserError(
            f"{folder}: is a folder of other files (no {RESULT_FILE}), which writing a result would delete; "
            "choose another output folder (-o DIR) or empty this one"
        )


@contextmanager
def result_folder(folder: Path) -> Iterator[Path]:
    """Yield a new empty folder beside ``folder`` (its parents created) to write a result into; when
    the block ends it replaces ``folder`` as a unit (``io.folders.atomic_folder``): an earlier result
    there — maps of another solver included — is gone, none is mixed in, and an error or Ctrl-C leaves
    the earlier folder as it was. ``check_result_folder`` first."""
    check_result_folder(folder)
    folder.parent.mkdir(parents=True, exist_ok=True)
    with atomic_folder(folder) as partial:
        yield partial


def write_result_folder(folder: Path, solved: SolvedCapture, summary: dict[str, Any]) -> str:
    """Write ``normal.npy``, ``normal.png``, the further maps, ``error.npy``/``error.png`` with ground
    truth, then ``result.json`` (returned as text) into ``folder``, created if needed."""
    text = summary_json(summary)
    folder.mkdir(parents=True, exist_ok=True)
    write_normal_npy(folder / "normal.npy", solved.normal)
    write_normal_png(folder / "normal.png", solved.normal, solved.mask)
    write_maps(folder, solved.maps)
    if solved.scored is not None:
        write_error_map(folder, solved.scored, summary["error_max_deg"])
    # Last, so a folder with result.json holds every file it lists.
    with psfmt.atomic_path(folder / RESULT_FILE) as tmp:
        tmp.write_text(text + "\n")
    return text
