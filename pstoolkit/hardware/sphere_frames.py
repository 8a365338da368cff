"""Light directions from frames of a chrome sphere, one frame per light (``sphere-frames``).

The source is a DiLiGenT-layout folder (``filenames.txt`` naming the images, one per light, and
``mask.png`` when there is one; its light tables are not read) or a capture's frames. The sphere is
the circle given as ``sphere=cx,cy,r``, else the circle through the outline of the mask (the folder's
``mask.png`` or the capture's ground truth), else of the silhouette in the brightest of all frames.
Each frame's highlight becomes a direction (``pstoolkit.hardware.highlight``), orthographically or
through the intrinsics (``intrinsics=K.txt``, else a perspective capture's own). With a matte
target under the same lights (``matte=``: a folder or capture of a white matte sphere) the light
intensities are fitted per light and channel by least squares to I = e·(n·l) over its lit pixels,
scaled to a mean of 1; without one they are 1.

The model written is ``sampled``: light k at k µs, like ``pstoolkit simulate --lights FILE``.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

import psfmt
from psfmt.camera import PERSPECTIVE
from pstoolkit.errors import UserError
from pstoolkit.hardware.highlight import disc, highlight_direction
from pstoolkit.hardware.lightcal import LightCalibration, LightFit
from pstoolkit.hardware.sphere import Circle, SphereView, circle_from_image, circle_from_mask, parse_circle
from pstoolkit.io.diligent_layout import FILENAMES, MASK, text_lines
from pstoolkit.io.normalmap import decode_image
from pstoolkit.optics.layouts import layout_light
from pstoolkit.plugin.options import Option

MAX_LIGHTS = 10000
MAX_PIXELS = 1 << 26
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
LIT_COSINE = 0.2
"""Matte pixels whose n·l is below this are left out of the intensity fit (terminator, shadow)."""
SATURATED = 0.98


def _inside(folder: Path, name: str, listing: Path) -> Path:
    """``folder/name`` for a plain file name listed in ``listing``; anything that could leave the
    folder is refused."""
    if not name or "/" in name or "\\" in name or name in (".", "..") or any(ord(ch) < 32 for ch in name):
        raise UserError(f"{listing}: {name[:60]!r} is not a file name inside {folder}")
    return folder / name


def _png_size(path: Path) -> tuple[int, int]:
    """(width, height) from a PNG's header, read before the image is decoded."""
    if not path.is_file():
        raise UserError(f"{path}: file does not exist")
    with open(path, "rb") as handle:
        head = handle.read(24)
    if len(head) < 24 or head[:8] != PNG_SIGNATURE or head[12:16] != b"IHDR":
        raise UserError(f"{path}: not a PNG image")
    width, height = int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    if not 0 < width * height <= MAX_PIXELS:
        raise UserError(f"{path}: {width}×{height} pixels, more than the {MAX_PIXELS:,} an image may have")
    return width, height


def _rgb(image: np.ndarray, path: Path) -> np.ndarray:
    """An image as OpenCV decodes it → (H, W, 3) float64 RGB in units of its full scale."""
    scale = float(np.iinfo(image.dtype).max) if np.issubdtype(image.dtype, np.integer) else 1.0
    x = np.asarray(image, dtype=np.float64) / scale
    if x.ndim == 2:
        return np.repeat(x[..., None], 3, axis=2)
    if x.ndim != 3 or x.shape[2] not in (3, 4):
        raise UserError(f"{path}: expected a grey or colour image")
    return x[..., 2::-1]


class FrameSource:
    """The frames of a folder or a capture, one per light, read one at a time as RGB (H, W, 3) float
    (1 = full scale); ``mask`` is the folder's or the ground truth's, or None; ``intrinsics`` a
    perspective capture's K, or None."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.mask: np.ndarray | None = None
        self.intrinsics: np.ndarray | None = None
        if path.is_dir():
            listing = path / FILENAMES
            names = text_lines(listing)
            if not names:
                raise UserError(f"{listing}: lists no images")
            if len(names) > MAX_LIGHTS:
                raise UserError(f"{listing}: lists {len(names)} images, more than {MAX_LIGHTS}")
            self.images = [_inside(path, name, listing) for name in names]
            sizes = {_png_size(p) for p in self.images}
            if len(sizes) != 1:
                raise UserError(f"{path}: the images differ in size ({', '.join(f'{w}×{h}' for w, h in sorted(sizes)[:3])} …)")
            (width, height), = sizes
            self.shape = (height, width)
            mask_path = path / MASK
            if mask_path.exists():
                if _png_size(mask_path) != (width, height):
                    raise UserError(f"{mask_path}: not the size of the images ({width}×{height})")
                self.mask = _rgb(self._decode(mask_path), mask_path).max(axis=2) > 0
            self.count = len(self.images)
        elif path.is_file():
            with psfmt.read(path) as capture:
                frames = capture.frames
                if frames is None or frames.count == 0:
                    raise UserError(f"{path}: holds no frames of the sphere")
                self.count, self.shape = frames.count, (frames.height, frames.width)
                truth = capture.ground_truth
                if truth is not None and truth.mask is not None:
                    self.mask = np.asarray(truth.mask, dtype=bool)
                if capture.calibration.camera_model == PERSPECTIVE:
                    self.intrinsics = capture.calibration.intrinsics
            self.images = []
        else:
            raise UserError(f"{path}: no such file or folder")

    @staticmethod
    def _decode(path: Path) -> np.ndarray:
        image = decode_image(path)
        if image is None:
            raise UserError(f"{path}: corrupted image (it cannot be decoded)")
        return image

    def frames(self) -> Iterator[np.ndarray]:
        """Each frame in light order, (H, W, 3) RGB float."""
        if self.images:
            for p in self.images:
                image = _rgb(self._decode(p), p)
                if image.shape[:2] != self.shape:
                    raise UserError(f"{p}: decodes to {image.shape[1]}×{image.shape[0]}, its header says otherwise")
                yield image
            return
        with psfmt.read(self.path) as capture:
            frames = capture.frames
            assert frames is not None
            for k in range(frames.count):
                x = np.asarray(frames.as_float(k), dtype=np.float64)
                if x.ndim == 2:
                    x = np.repeat(x[..., None], 3, axis=2)
                elif frames.color_order.upper() == "BGR":
                    x = x[..., ::-1]
                yield x[..., :3] if x.shape[2] >= 3 else np.repeat(x[..., :1], 3, axis=2)


def find_circle(source: FrameSource, given: str, level: float, what: str) -> tuple[Circle, np.ndarray | None]:
    """The sphere's outline as a circle and its points (None when given): ``given`` (``cx,cy,r``),
    else the source's mask, else the silhouette in the per-pixel maximum over its frames."""
    if given:
        return parse_circle(given, what), None
    if source.mask is not None:
        return circle_from_mask(source.mask, f"{source.path}: mask")
    brightest = np.zeros(source.shape)
    for frame in source.frames():
        np.maximum(brightest, frame.mean(axis=2), out=brightest)
    return circle_from_image(brightest, level, f"{source.path}: silhouette")


def read_intrinsics(text: str, fallback: np.ndarray | None) -> np.ndarray | None:
    """The 3×3 K of a ``K.txt`` path, or ``fallback`` when none is given."""
    if not text:
        return fallback
    path = Path(text)
    try:
        k = np.loadtxt(path, dtype=np.float64)
    except (OSError, ValueError) as exc:
        raise UserError(f"{path}: cannot read intrinsics ({str(exc).strip().splitlines()[0][:80]})") from None
    if k.size != 9:
        raise UserError(f"{path}: expected a 3×3 matrix K, got {k.size} number(s)")
    return k.reshape(3, 3)


def matte_intensities(
    source: FrameSource, outline: tuple[Circle, np.ndarray | None], directions: np.ndarray, intrinsics: np.ndarray | None
) -> np.ndarray:
    """(K, 3) RGB light intensities from a matte sphere under the same K lights: per light and
    channel the least-squares e of I = e·(n·l) over lit, unsaturated pixels, scaled to mean 1."""
    if source.count != len(directions):
        raise UserError(f"{source.path}: {source.count} matte images, but {len(directions)} lights were found on the chrome sphere")
    sphere = SphereView.build(outline[0], intrinsics, outline[1])
    rows, cols = np.nonzero(disc(source.shape, sphere, margin_px=2.0))
    normal, _, _ = sphere.normals(cols, rows)
    out = np.zeros((len(directions), 3))
    for k, frame in enumerate(source.frames()):
        shading = normal @ directions[k]
        values = frame[rows, cols]
        use = (shading > LIT_COSINE) & np.all(values < SATURATED, axis=1)
        if use.sum() < 10:
            raise UserError(f"{source.path}: image {k + 1} has too few lit matte pixels to fit its light's intensity")
        s = shading[use]
        out[k] = s @ values[use] / (s @ s)
    mean = float(out.mean())
    if not mean > 0:
        raise UserError(f"{source.path}: the matte sphere is dark under every light")
    return out / mean


class SphereFrames(LightCalibration):
    """Chrome sphere, one frame per light → a ``sampled`` model of the measured directions."""

    name: ClassVar[str] = "sphere-frames"
    summary: ClassVar[str] = "chrome sphere in one frame per light (folder or capture): highlight → direction, sampled model"
    options: ClassVar[tuple[Option, ...]] = (
        Option("sphere", str, "", "the sphere's outline cx,cy,r in frame pixels (default: from the mask or the silhouette)"),
        Option("intrinsics", str, "", "K.txt of a pinhole camera (default: the capture's, else orthographic)"),
        Option("level", float, 0.5, "highlight threshold, fraction from the sphere's median to its peak", minimum=0.05, maximum=0.95),
        Option("silhouette", float, 0.05, "silhouette threshold in the brightest frame, when no mask or circle is given", minimum=0.001, maximum=0.95),
        Option("matte", str, "", "folder or capture of a matte sphere under the same lights, for the intensities"),
        Option("matte_sphere", str, "", "the matte sphere's outline cx,cy,r (default: from its mask or silhouette)"),
    )

    @classmethod
    def accepts(cls, source: Path) -> bool:
        if source.is_dir():
            return True
        try:
            with psfmt.read(source) as capture:
                return capture.events is None or len(capture.events) == 0
        except (psfmt.FormatError, OSError):
            return False

    def calibrate(self, source: Path, **options: Any) -> LightFit:
        frames = FrameSource(source)
        circle, outline = find_circle(frames, options["sphere"], options["silhouette"], "--sphere")
        intrinsics = read_intrinsics(options["intrinsics"], frames.intrinsics)
        sphere = SphereView.build(circle, intrinsics, outline)
        inside = disc(frames.shape, sphere)
        directions = []
        for k, frame in enumerate(frames.frames()):
            direction = highlight_direction(frame.mean(axis=2), sphere, options["level"], inside)
            if direction is None:
                raise UserError(f"{source}: image {k + 1} shows no highlight on the sphere")
            directions.append(direction)
        l = np.array(directions)
        if options["matte"]:
            matte = FrameSource(Path(options["matte"]))
            matte_outline = find_circle(matte, options["matte_sphere"], options["silhouette"], "matte_sphere")
            intensities = matte_intensities(matte, matte_outline, l, intrinsics)
        else:
            intensities = np.ones_like(l)
        light = layout_light(l, intensities)
        return LightFit(
            spec=light.to_spec(),
            directions=l,
            intensities=intensities,
            times_us=light.times_us,
            details={
                "sphere_px": [circle.cx, circle.cy, circle.r],
                "camera": "orthographic" if intrinsics is None else "perspective",
                "intensities_from": options["matte"] or None,
            },
        )
