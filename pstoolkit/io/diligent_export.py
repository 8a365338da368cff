"""A classic capture as a DiLiGenT object folder (``pstoolkit export CAPTURE --frames diligent -o DIR``),
which ``pstoolkit convert diligent`` and other photometric-stereo code read back.

    written = export_diligent(Path("grid.h5"), Path("blobsPNG"))

The capture must hold frames under instantaneous lights (a per-frame light direction; no exposure
windows). The folder (layout in ``pstoolkit.io.diligent_layout``) gets:

- ``001.png`` … one 16-bit RGB PNG per frame (stored BGR, as OpenCV writes them), the frame's values
  relative to its saturation scaled to 65535: round((v − black) · 65535 / (saturation − black)),
  which is ×257 exactly for 8-bit frames, the identity for 16-bit ones, and for 12-bit ones a value
  that reads back to v exactly (round(w · 4095 / 65535) = v); grey frames are written to all three
  channels. Images are not divided by the light intensities (DiLiGenT's convention);
- ``filenames.txt``; ``light_directions.txt`` and ``light_intensities.txt`` (RGB order; 1 when the
  capture stores none), numbers to 17 significant digits so they read back exactly;
- ``mask.png`` (uint8, 3 channels, 0/255): the ground-truth mask, or else every pixel brighter than
  ``MASK_LEVEL`` of white in some channel of some frame;
- ``Normal_gt.mat`` (MATLAB v5, variable ``Normal_gt``, float64 (H, W, 3), 0 outside the mask) when
  the capture has ground-truth normals.

The folder is written as a unit (``pstoolkit.io.folders.atomic_folder``): an existing non-empty folder
is an error unless ``force``, and then replaced only once the new one is complete. Frames are read
and written one at a time, so a capture of any length exports in the memory of one frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.io

import psfmt
from psfmt.atomic import check_target
from pstoolkit._shared.progress import Progress, no_progress
from pstoolkit.errors import UserError
from pstoolkit.io.diligent_layout import DIRECTIONS, FILENAMES, INTENSITIES, MASK, NORMAL, NORMAL_VARIABLE
from pstoolkit.io.folders import atomic_folder
from pstoolkit.io.normalmap import write_png

PNG_WHITE = 65535
MASK_LEVEL = 1.0 / 256.0
"""Without a ground-truth mask, a pixel is inside when some frame holds more than this share of white."""


@dataclass
class ExportedFolder:
    """What ``export_diligent`` wrote: the folder, the image count and size, where the mask came from
    (``"ground truth"`` or ``"frames"``) and whether ``Normal_gt.mat`` was written."""

    folder: Path
    images: int
    height: int
    width: int
    mask_source: str
    normal: bool


def to_png_levels(frame: np.ndarray, frames: psfmt.Frames) -> np.ndarray:
    """(H, W, 3) uint16 of one stored frame (H, W, C): its value relative to saturation (black level
    removed) times 65535, rounded and clipped; grey frames repeated to RGB."""
    black = float(frames.black_level)
    scale = PNG_WHITE / (float(frames.saturation) - black)
    levels = np.clip(np.rint((np.asarray(frame, dtype=np.float64) - black) * scale), 0, PNG_WHITE).astype(np.uint16)
    return np.repeat(levels, 3, axis=-1) if levels.shape[-1] == 1 else levels


def check_exportable(capture: psfmt.Capture, source: Path) -> psfmt.Frames:
    """The capture's frames, or UserError naming ``source`` when they are not a classic capture's."""
    frames = capture.frames
    if frames is None:
        raise UserError(f"{source}: holds no frames to export")
    if frames.has_windows:
        raise UserError(
            f"{source}: a {capture.kind} capture of long exposures cannot be a DiLiGenT folder, which needs one "
            "instantaneous light per frame (a classic capture: simulate --discrete-lights N or --lights grid|FILE)"
        )
    if not frames.has_instant_lights:
        raise UserError(f"{source}: the frames have no light directions, which a DiLiGenT folder needs")
    if frames.response != "linear":
        raise UserError(f"{source}: frames with a {frames.response!r} response; a DiLiGenT folder holds linear images")
    if frames.channels not in (1, 3):
        raise UserError(f"{source}: frames with {frames.channels} channels; a DiLiGenT folder holds RGB or grey images")
    if not float(frames.saturation) > float(frames.black_level):
        raise UserError(f"{source}: frame saturation {frames.saturation:g} is not above the black level {frames.black_level:g}")
    return frames


def _truth(capture: psfmt.Capture, shape: tuple[int, int], source: Path) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Ground-truth (mask, normal) at the frames' size, each None when the capture lacks it; a
    capture with normals but no mask takes the pixels whose normal is non-zero."""
    gt = capture.ground_truth
    if gt is None:
        return None, None
    normal = None if gt.normal is None else np.asarray(gt.normal, dtype=np.float64)
    mask = None if gt.mask is None else np.asarray(gt.mask, dtype=bool)
    if mask is None and normal is not None:
        mask = np.linalg.norm(normal, axis=-1) > 0
    for name, array in (("mask", mask), ("normal", normal)):
        if array is not None and array.shape[:2] != shape:
            raise UserError(f"{source}: ground-truth {name} is {array.shape[1]}×{array.shape[0]}, the frames {shape[1]}×{shape[0]}")
    if normal is not None and mask is not None:
        normal = np.where(mask[..., None], normal, 0.0)
    return mask, normal


def _check_target(folder: Path, source: Path, force: bool) -> None:
    if not folder.parent.is_dir():
        raise UserError(f"{folder}: folder {folder.parent} does not exist")
    check_target(folder, [source], folder=folder.is_dir() or folder.is_symlink())
    if folder.exists() and not folder.is_dir():
        raise UserError(f"{folder}: is a file, not a folder")
    if folder.is_dir() and any(folder.iterdir()) and not force:
        raise UserError(f"{folder}: folder exists and is not empty (give --force to replace it)")


def _write_table(path: Path, table: np.ndarray) -> None:
    path.write_text("".join(" ".join(f"{v:.17g}" for v in row) + "\n" for row in table), encoding="utf-8")


def export_diligent(source: Path, folder: Path, *, force: bool = False, progress: Progress = no_progress) -> ExportedFolder:
    """Write the classic capture ``source`` as the DiLiGenT object folder ``folder`` (see the module
    docstring). UserError, with nothing written, for a capture that is not a classic one, a
    non-empty ``folder`` without ``force``, or a capture without ground truth whose frames are all
    dark (no mask)."""
    _check_target(folder, source, force)
    with psfmt.read(source) as capture:
        frames = check_exportable(capture, source)
        count, shape = frames.count, (frames.height, frames.width)
        mask, normal = _truth(capture, shape, source)
        assert frames.light_direction is not None
        intensity = frames.light_intensity if frames.light_intensity is not None else np.ones((count, 3))
        digits = max(3, len(str(count)))
        names = [f"{k + 1:0{digits}d}.png" for k in range(count)]
        lit = np.zeros(shape, dtype=bool)
        with atomic_folder(folder) as partial:
            for k, name in enumerate(names):
                frame = frames.frame(k)
                if frame.dtype.kind == "f" and not np.all(np.isfinite(frame)):
                    raise UserError(f"{source}: frame {k} holds NaN or infinite values")
                levels = to_png_levels(frame, frames)
                lit |= np.any(levels > MASK_LEVEL * PNG_WHITE, axis=-1)
                write_png(partial / name, levels)
                progress((k + 1) / count, "images")
            mask_source = "ground truth" if mask is not None else "frames"
            mask = lit if mask is None else mask
            if not mask.any():
                raise UserError(f"{source}: every frame is dark and there is no ground-truth mask: no mask.png to write")
            write_png(partial / MASK, np.repeat(mask[..., None], 3, axis=-1).astype(np.uint8) * np.uint8(255))
            (partial / FILENAMES).write_text("".join(f"{name}\n" for name in names), encoding="utf-8")
            _write_table(partial / DIRECTIONS, frames.light_direction)
            _write_table(partial / INTENSITIES, intensity)
            if normal is not None:
                scipy.io.savemat(partial / NORMAL, {NORMAL_VARIABLE: normal.astype(np.float64)})
    return ExportedFolder(folder, count, shape[0], shape[1], mask_source, normal is not None)
