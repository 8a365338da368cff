"""Normal maps on disk in the community convention: RGB = (n + 1)/2 scaled to the full 8- or 16-bit
range, R = x right, G = y up, B = z towards the camera, background 0 (a pixel facing the camera is
(128, 128, 255) in 8 bit). Also float32 .npy maps, and the DiLiGenT-geometry folder layout.

OpenCV stores colour images as BGR, so every read and write here swaps the channel order.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import cv2
import numpy as np

from psfmt import atomic_path
from psfmt.text import printable
from pstoolkit._shared.vectors import unit
from pstoolkit.errors import UserError

_DTYPES = {8: np.uint8, 16: np.uint16}




def _check_normal(normal: np.ndarray, what: str) -> np.ndarray:
    array = np.asarray(normal, dtype=np.float64)
    if array.ndim != 3 or array.shape[2] != 3:
        raise UserError(f"{what}: normal map has shape {array.shape}, expected (H, W, 3)")
    return array


def normal_to_rgb(normal: np.ndarray, mask: np.ndarray | None = None, bits: int = 16) -> np.ndarray:
    """Encode (H, W, 3) normals as RGB uint16 (bits=16) or uint8 (bits=8): round((n + 1)/2 · (2^bits − 1)),
    half up, 0 outside ``mask`` (default: where the normal is non-zero). Normals are normalised first."""
    if bits not in _DTYPES:
        raise UserError(f"normal map bit depth must be 8 or 16, got {bits}")
    n = _check_normal(normal, "normal_to_rgb")
    mask = np.linalg.norm(n, axis=-1) > 0 if mask is None else np.asarray(mask, dtype=bool)
    if mask.shape != n.shape[:2]:
        raise UserError(f"mask of shape {mask.shape} does not fit a {n.shape[0]}×{n.shape[1]} normal map")
    top = float(2**bits - 1)
    rgb = np.clip(np.floor((unit(n) + 1.0) / 2.0 * top + 0.5), 0, top).astype(_DTYPES[bits])
    rgb[~mask] = 0
    return rgb


def rgb_to_normal(rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Decode an 8- or 16-bit RGB normal map: (normal float32 (H, W, 3) renormalised, 0 in the
    background; mask bool (H, W), False where all three channels are 0)."""
    array = np.asarray(rgb)
    if array.ndim != 3 or array.shape[2] != 3:
        raise UserError(f"normal image has shape {array.shape}, expected (H, W, 3) RGB")
    if array.dtype not in (np.uint8, np.uint16):
        raise UserError(f"normal image has dtype {array.dtype}, expected uint8 or uint16")
    top = float(np.iinfo(array.dtype).max)
    mask = np.any(array != 0, axis=-1)
    normal = unit(array.astype(np.float64) / top * 2.0 - 1.0)
    normal[~mask] = 0.0
    return normal.astype(np.float32), mask


def _target(path: str | os.PathLike[str]) -> Path:
    path = Path(path)
    if not path.parent.is_dir():
        raise UserError(f"{path}: folder {path.parent} does not exist")
    return path


def _encode_png(image: np.ndarray) -> bytes:
    """PNG bytes of a uint8 or uint16 image: grey (H, W) or RGB (H, W, 3), channels in RGB order."""
    array = np.asarray(image)
    if array.dtype not in (np.uint8, np.uint16):
        raise UserError(f"PNG image has dtype {array.dtype}, expected uint8 or uint16")
    if array.ndim == 3 and array.shape[2] == 3:
        array = array[..., ::-1]
    elif array.ndim != 2:
        raise UserError(f"PNG image has shape {array.shape}, expected (H, W) grey or (H, W, 3) RGB")
    ok, encoded = cv2.imencode(".png", np.ascontiguousarray(array))
    if not ok:
        raise UserError(f"OpenCV could not encode a {array.dtype} {array.shape} image as PNG")
    return encoded.tobytes()


def write_png(path: str | os.PathLike[str], image: np.ndarray) -> None:
    """Write a uint8/uint16 grey (H, W) or RGB (H, W, 3) image as PNG atomically."""
    path = _target(path)
    # Encode in memory: the atomic temporary file has no .png suffix for cv2.imwrite to go by.
    data = _encode_png(image)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_normal_png(path: str | os.PathLike[str], normal: np.ndarray, mask: np.ndarray | None = None, bits: int = 16) -> None:
    """Write a normal map PNG (8 or 16 bit) atomically."""
    write_png(path, normal_to_rgb(normal, mask, bits))


@contextmanager
def _quiet_stderr() -> Iterator[None]:
    """Send what C libraries write to stderr (file descriptor 2) nowhere for the block: libpng prints
    "libpng error: …" on a damaged image before OpenCV returns None, and the caller says in one line
    of its own what failed."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def decode_image(path: Path) -> np.ndarray | None:
    """The image file at ``path`` as stored (OpenCV order: BGR for colour, its own bit depth), or None
    when OpenCV cannot decode it; the decoder's own complaints are not printed."""
    data = np.fromfile(path, dtype=np.uint8)
    with _quiet_stderr():
        return cv2.imdecode(data, cv2.IMREAD_UNCHANGED)


def _read_image(path: Path) -> np.ndarray:
    if not path.is_file():
        raise UserError(f"{path}: file does not exist")
    image = decode_image(path)
    if image is None:
        raise UserError(f"{path}: not a readable image")
    return image


def read_normal_png(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """Read an 8- or 16-bit RGB normal map PNG: (normal float32 (H, W, 3), mask bool (H, W))."""
    path = Path(path)
    image = _read_image(path)
    if image.ndim != 3 or image.shape[2] != 3:
        raise UserError(f"{path}: expected a 3-channel RGB normal map, got shape {image.shape}")
    try:
        return rgb_to_normal(image[..., ::-1])
    except UserError as exc:
        raise UserError(f"{path}: {exc}") from None


def write_normal_npy(path: str | os.PathLike[str], normal: np.ndarray) -> None:
    """Write normals as float32 (H, W, 3) .npy atomically."""
    path = _target(path)
    write_npy(path, _check_normal(normal, str(path)).astype(np.float32))


def write_npy(path: str | os.PathLike[str], array: np.ndarray) -> None:
    """Write an array as .npy atomically (no pickles)."""
    with atomic_path(path) as tmp:
        # A file handle, because np.save appends ".npy" to a path that lacks it.
        with open(tmp, "wb") as fh:
            np.save(fh, array, allow_pickle=False)


def npy_header(path: Path) -> tuple[tuple[int, ...], np.dtype]:
    """The (shape, dtype) a .npy file declares, once it is known to be an array of numbers whose
    declared size the file holds: a crafted header (a negative or 2⁶²-long axis, more data than
    stored) is a UserError naming the file before anything is allocated or memory-mapped."""
    try:
        with open(path, "rb") as fh:
            version = np.lib.format.read_magic(fh)
            if version not in ((1, 0), (2, 0)):
                raise ValueError(f".npy format version {version[0]}.{version[1]} is not read")
            reader = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            shape, _, dtype = reader(fh)
            offset = fh.tell()
            size = os.fstat(fh.fileno()).st_size
    except (ValueError, OSError, EOFError, SyntaxError, OverflowError) as exc:
        raise UserError(f"{path}: not a readable .npy array ({printable(str(exc))})") from None
    if dtype.hasobject or dtype.kind not in "biuf":
        raise UserError(f"{path}: expected an array of numbers, got {printable(str(dtype))}")
    if any(n < 0 for n in shape):
        raise UserError(f"{path}: the .npy header declares a negative shape {shape}")
    count = 1
    for n in shape:
        count *= n
    if count * dtype.itemsize > size - offset:
        raise UserError(f"{path}: the .npy header declares {count * dtype.itemsize} bytes of data, the file holds {size - offset}")
    return tuple(shape), dtype


def read_npy(path: str | os.PathLike[str]) -> np.ndarray:
    """Read a numeric .npy array; a missing file, a damaged one, one whose header claims more than
    it holds (``npy_header``) or one that holds Python objects (which would need unpickling, never
    done) is a UserError."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: file does not exist")
    npy_header(path)
    try:
        array = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise UserError(f"{path}: not a readable .npy array ({printable(str(exc))})") from None
    if not isinstance(array, np.ndarray) or array.dtype.kind not in "biuf":
        raise UserError(f"{path}: expected an array of numbers, got {getattr(array, 'dtype', type(array).__name__)}")
    return array


def read_normal_npy(path: str | os.PathLike[str]) -> np.ndarray:
    """Read a float32 (H, W, 3) normal map .npy."""
    path = Path(path)
    array = read_npy(path)
    if array.ndim != 3 or array.shape[2] != 3 or array.dtype.kind != "f":
        raise UserError(f"{path}: expected a float (H, W, 3) normal map, got {array.dtype} {array.shape}")
    return array.astype(np.float32, copy=False)


def read_geometry_folder(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read a DiLiGenT-geometry folder: ``normal_map.png`` (16-bit, n = v/65535·2 − 1), ``mask.png``
    (non-zero inside) and ``depth_gt.npz`` (key ``depth_gt``). Returns (normal float32 (H, W, 3) unit
    inside the mask and 0 outside, mask bool (H, W), depth float32 (H, W) as stored)."""
    folder = Path(path)
    if not folder.is_dir():
        raise UserError(f"{folder}: geometry folder does not exist")
    normal_path, mask_path, depth_path = folder / "normal_map.png", folder / "mask.png", folder / "depth_gt.npz"
    image = _read_image(normal_path)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint16:
        raise UserError(f"{normal_path}: expected a 16-bit RGB image, got {image.dtype} {image.shape}")
    mask_image = _read_image(mask_path)
    mask = mask_image > 0 if mask_image.ndim == 2 else np.any(mask_image > 0, axis=-1)
    if mask.shape != image.shape[:2]:
        raise UserError(f"{mask_path}: mask is {mask.shape[0]}×{mask.shape[1]}, the normal map {image.shape[0]}×{image.shape[1]}")
    # The background of these maps is not 0 (often 65535), so the mask comes from mask.png alone.
    normal = unit(image[..., ::-1].astype(np.float64) / 65535.0 * 2.0 - 1.0)
    normal[~mask] = 0.0
    if not depth_path.is_file():
        raise UserError(f"{depth_path}: file does not exist")
    try:
        with np.load(depth_path, allow_pickle=False) as archive:
            depth = np.asarray(archive["depth_gt"], dtype=np.float32)
    except KeyError:
        raise UserError(f"{depth_path}: key 'depth_gt' is missing") from None
    except (ValueError, OSError) as exc:
        raise UserError(f"{depth_path}: not a readable .npz archive ({exc})") from None
    if depth.shape != mask.shape:
        raise UserError(f"{depth_path}: depth is {depth.shape}, the normal map {image.shape[0]}×{image.shape[1]}")
    return normal.astype(np.float32), mask, depth


UNSOLVED_RGB = (128, 128, 128)
"""``error.png``'s colour of a pixel the solver left unsolved."""


def error_to_rgb(error_deg: np.ndarray, error_max_deg: float, solved: np.ndarray | None = None) -> np.ndarray:
    """8-bit RGB (H, W, 3) of an angular-error map through the Turbo colormap over 0…``error_max_deg``
    degrees (larger errors saturate); NaN pixels (outside the mask) are black, pixels outside
    ``solved`` (H, W) bool (None: all solved) ``UNSOLVED_RGB``."""
    inside = np.isfinite(error_deg)
    level = np.clip(np.where(inside, error_deg, 0.0) / error_max_deg * 255.0 + 0.5, 0, 255).astype(np.uint8)
    rgb = cv2.applyColorMap(level, cv2.COLORMAP_TURBO)[..., ::-1].copy()
    if solved is not None:
        rgb[inside & ~solved] = UNSOLVED_RGB
    rgb[~inside] = 0
    return rgb
