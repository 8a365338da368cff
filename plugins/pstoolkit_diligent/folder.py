"""One DiLiGenT-layout object folder (Shi et al. 2016; docs/converters.md), checked completely before anything is converted.

    obj = scan_object(Path("pmsData/ballPNG"), require_normal=True)   # UserError on any problem
    rgb = obj.image(0)                                                 # (H, W, 3) uint16, RGB order

Layout: the images named in ``filenames.txt`` (16-bit RGB PNG, stored BGR as OpenCV writes them),
``light_directions.txt`` and ``light_intensities.txt`` (one ``x y z`` / ``r g b`` line per image; the
intensities in RGB order), ``mask.png`` (non-zero inside) and ``Normal_gt.mat`` (variable
``Normal_gt``, float64 (H, W, 3)). Lights and normals share the camera frame of the capture format
(x right, y up, z towards the camera), so they are taken as they are.

Every file read lies inside the object folder: a name in ``filenames.txt`` that is absolute, climbs
out with ``..`` or reaches out through a symbolic link is refused, as is a fixed file that is a link
to elsewhere (a downloaded dataset must not make the converter read the user's other files).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.io

from pstoolkit import UserError
from pstoolkit.io.diligent_layout import (
    DIRECTIONS,
    FILENAMES,
    INTENSITIES,
    MASK,
    NORMAL,
    NORMAL_VARIABLE,
    read_directions,
    read_intensities,
    require_file,
    text_lines,
)
from pstoolkit_diligent.png import check_png, decode


@dataclass
class ObjectFolder:
    """A checked object folder: image paths in ``filenames.txt`` order with their unit light
    directions and RGB intensities (K, 3), the mask (H, W) and the ground-truth normals (H, W, 3),
    0 outside the mask, when present."""

    path: Path
    images: list[Path]
    directions: np.ndarray
    intensities: np.ndarray
    mask: np.ndarray
    normal: np.ndarray | None

    @property
    def height(self) -> int:
        return int(self.mask.shape[0])

    @property
    def width(self) -> int:
        return int(self.mask.shape[1])

    def image(self, k: int) -> np.ndarray:
        """Image ``k`` as (H, W, 3) uint16 in RGB order."""
        path = self.images[k]
        image = decode(path)
        if image.dtype != np.uint16 or image.shape != (self.height, self.width, 3):
            raise UserError(f"{path}: decoded as {image.dtype} {image.shape}, expected uint16 ({self.height}, {self.width}, 3)")
        return image[..., ::-1]


def _inside(folder: Path, name: str, listed_in: Path | None = None) -> Path:
    """``folder / name``, refused (UserError) unless it stays inside ``folder`` once symbolic links
    and ``..`` are resolved; ``listed_in`` is the file that named it."""
    path = folder / name
    if not Path(name).is_absolute() and path.resolve().is_relative_to(folder.resolve()):
        return path
    where = f"{listed_in}: {name!r}" if listed_in is not None else str(path)
    raise UserError(f"{where} lies outside the object folder {folder}: refused")


def _mask(path: Path, height: int, width: int) -> np.ndarray:
    header = check_png(path)
    if (header.height, header.width) != (height, width):
        raise UserError(f"{path}: mask is {header.width}×{header.height}, the images {width}×{height}")
    image = decode(path)
    mask = image > 0 if image.ndim == 2 else np.any(image > 0, axis=-1)
    if not mask.any():
        raise UserError(f"{path}: the mask is empty")
    return mask


def _normal(path: Path, mask: np.ndarray) -> np.ndarray:
    try:
        content = scipy.io.loadmat(path, variable_names=[NORMAL_VARIABLE])
    # scipy reports a malformed file through any of these, a MATLAB v7.3 (HDF5) file as NotImplementedError
    except (ValueError, TypeError, OSError, NotImplementedError, scipy.io.matlab.MatReadError) as exc:
        raise UserError(f"{path}: not a readable MATLAB v5 file ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from None
    if NORMAL_VARIABLE not in content:
        raise UserError(f"{path}: variable {NORMAL_VARIABLE!r} is missing")
    normal = np.asarray(content[NORMAL_VARIABLE])
    if normal.shape != (*mask.shape, 3) or normal.dtype.kind not in "fi":
        raise UserError(f"{path}: {NORMAL_VARIABLE} is {normal.dtype} {normal.shape}, expected real ({mask.shape[0]}, {mask.shape[1]}, 3)")
    normal = normal.astype(np.float64)
    if not np.all(np.isfinite(normal)):
        raise UserError(f"{path}: {NORMAL_VARIABLE} holds NaN or infinity")
    norm = np.linalg.norm(normal, axis=-1, keepdims=True)
    return np.where(mask[..., None] & (norm > 0), normal / np.maximum(norm, 1e-300), 0.0)


def scan_object(folder: Path, require_normal: bool) -> ObjectFolder:
    """Check every file of an object folder (present, counts agree, 16-bit RGB PNGs of one size with
    intact checksums, mask and ground truth of that size) and read the small ones. Raises UserError
    naming the file and the problem; ``Normal_gt.mat`` may be absent unless ``require_normal``."""
    if not folder.is_dir():
        raise UserError(f"{folder}: folder does not exist")
    files = (FILENAMES, DIRECTIONS, INTENSITIES, MASK, NORMAL)
    listing, lights, colours, mask_path, normal_path = (_inside(folder, name) for name in files)
    names = text_lines(listing)
    for path in (lights, colours, mask_path):
        require_file(path)
    if require_normal:
        require_file(normal_path)
    directions = read_directions(lights)
    intensities = read_intensities(colours)
    counts = {FILENAMES: len(names), DIRECTIONS: len(directions), INTENSITIES: len(intensities)}
    if len(set(counts.values())) != 1:
        listed = ", ".join(f"{name} has {count}" for name, count in counts.items())
        raise UserError(f"{folder}: the numbers of images and lights differ ({listed} lines)")
    if not names:
        raise UserError(f"{listing}: lists no images")
    images = [_inside(folder, name, listing) for name in names]
    size: tuple[int, int] | None = None
    for path in images:
        header = check_png(path)
        if header.bit_depth != 16:
            raise UserError(f"{path}: {header.bit_depth}-bit image, expected a 16-bit PNG")
        if header.channels != 3:
            raise UserError(f"{path}: {header.channels}-channel image, expected RGB")
        if size is None:
            size = (header.height, header.width)
        elif (header.height, header.width) != size:
            raise UserError(f"{path}: image is {header.width}×{header.height}, {images[0].name} is {size[1]}×{size[0]}")
    assert size is not None
    mask = _mask(mask_path, *size)
    normal = _normal(normal_path, mask) if normal_path.is_file() else None
    return ObjectFolder(folder, images, directions, intensities, mask, normal)
