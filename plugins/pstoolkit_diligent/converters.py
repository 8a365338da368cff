"""The ``diligent`` and ``diligent-pi`` converters: DiLiGenT-layout object folders → captures.

Default output (both): a frames-only capture of the 16-bit images exactly as stored (uint16, RGB
order, saturation 65535) with each frame's unit light direction and RGB ``light_intensity`` from
``light_intensities.txt``, the mask and ``Normal_gt.mat`` when present. The division by the
intensities is left to the reader, as the format defines for instantaneous frames (spec §5): the
values stay exact and a clipped pixel stays recognisable at 65535, which no single saturation level
could mark after a per-frame, per-channel division. ``diligent --semi-real`` and
``--discrete-lights K`` write the semi-real captures of ``semireal``.

Every object folder named is checked completely (``folder.scan_object``) before the first file is
written; each file is written atomically.
"""

from __future__ import annotations

import json
from abc import abstractmethod
from collections.abc import Callable
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

import psfmt
import pstoolkit
from psfmt import REFRACTORY_RULES
from pstoolkit import Converter, Option, Progress, UserError
from pstoolkit.io.diligent_layout import FILENAMES
from pstoolkit.sim.sensor import MAX_NOISE_HZ, MAX_RATE_SPREAD_DECADES, SENSOR_PRESETS
from pstoolkit_diligent.folder import ObjectFolder, scan_object
from pstoolkit_diligent.geometry import (
    Square,
    area_resize,
    crop,
    resize_truth,
    square_around,
)
from pstoolkit_diligent.semireal import (
    MARGIN_PX,
    SemiRealConfig,
    check_grid,
    write_semi_real,
)

_SEMI = SemiRealConfig()
PRESET_OVERRIDES = (
    "contrast_sigma", "refractory_us", "refractory_rule", "leak_hz", "shot_noise_hz", "rate_spread_decades",
    "hot_pixel_fraction", "hot_pixel_hz", "bit_depth", "black_level", "full_well_e", "read_noise_e",
)
"""The semi-real options that override a field of the --sensor preset when given (None: the preset's)."""
UINT16_WHITE = 65535

SELECTION_OPTIONS = (
    Option("object", str, (), "object folder under the SRC root (ball or ballPNG); repeat for several", multiple=True),
    Option("all", bool, False, "convert every object folder (one holding filenames.txt) under the SRC root, each to OUT/<object>.h5"),
)


def _targets(src: Path, options: dict[str, Any], suffix: str) -> list[tuple[str, Path]]:
    """(output stem, object folder) pairs: SRC itself, or the objects named under the root SRC.
    ``suffix`` is the dataset's folder suffix ("PNG" for ballPNG) that names may omit."""
    names, every = options["object"], options["all"]
    is_object = (src / FILENAMES).is_file()
    if is_object and (names or every):
        raise UserError(f"{src}: is an object folder; --object and --all need the dataset root folder")
    if is_object:
        return [(src.name.removesuffix(suffix) or src.name, src)]
    if not src.is_dir():
        raise UserError(f"{src}: not a folder")
    if names and every:
        raise UserError("give --object NAME or --all, not both")
    if every:
        folders = sorted(p for p in src.iterdir() if (p / FILENAMES).is_file())
        if not folders:
            raise UserError(f"{src}: holds no object folder (a folder with {FILENAMES})")
    elif names:
        folders = []
        for name in names:
            candidates = [src / name, src / f"{name}{suffix}"] if suffix and not name.endswith(suffix) else [src / name]
            found = next((c for c in candidates if c.is_dir()), None)
            if found is None:
                raise UserError(f"{src}: no object folder {' or '.join(c.name for c in candidates)}")
            folders.append(found)
    else:
        raise UserError(f"{src}: has no {FILENAMES}; give an object folder, or the dataset root with --object NAME or --all")
    stems = [f.name.removesuffix(suffix) or f.name for f in folders]
    if len(set(stems)) != len(stems):
        raise UserError(f"an object is named more than once ({', '.join(stems)})")
    return list(zip(stems, folders))


def _outputs(out: Path, stems: list[str], folder: bool = False) -> list[Path]:
    """One object → OUT (or OUT/<object>.h5 when OUT is a folder); several, or any number with
    ``folder`` (``--all``, where how many objects the root holds is not the user's choice, so the
    output's kind must not depend on it) → OUT/<object>.h5, OUT created."""
    if len(stems) == 1 and not folder and not out.is_dir():
        if not out.parent.is_dir():
            raise UserError(f"{out}: folder {out.parent} does not exist")
        return [out]
    if out.exists() and not out.is_dir():
        why = "--all writes an output folder" if len(stems) == 1 else f"{len(stems)} objects need an output folder"
        raise UserError(f"{out}: is a file, but {why}")
    if not out.parent.is_dir():
        raise UserError(f"{out}: folder {out.parent} does not exist")
    return [out / f"{stem}.h5" for stem in stems]


class _Folders(Converter):
    """Shared by the DiLiGenT-layout converters: selection of objects, checks, output paths."""

    folder_suffix: ClassVar[str] = ""
    requires_normal: ClassVar[bool] = False

    def convert(self, src: Path, out: Path, options: dict[str, Any], progress: Progress) -> list[Path]:
        self.check_options(options)
        targets = _targets(src, options, self.folder_suffix)
        paths = _outputs(out, [stem for stem, _ in targets], folder=options["all"])
        objects = [scan_object(folder, self.requires_normal) for _, folder in targets]
        for obj in objects:
            self.check_object(obj, options)
        if paths != [out]:
            out.mkdir(exist_ok=True)
        settings = json.dumps({k: list(v) if isinstance(v, tuple) else v for k, v in options.items()}, sort_keys=True)
        for i, (obj, path) in enumerate(zip(objects, paths)):
            description = f"{obj.path.name} converted by pstoolkit convert {self.name} {settings}"
            with psfmt.CaptureWriter(path, description=description, creator="pstoolkit", creator_version=pstoolkit.__version__) as writer:
                self.write(obj, writer, options, lambda f, m, i=i: progress((i + f) / len(objects), m))
        return paths

    def check_options(self, options: dict[str, Any]) -> None:
        """Raise UserError for an option combination the converter rejects."""

    def check_object(self, obj: ObjectFolder, options: dict[str, Any]) -> None:
        """Raise UserError when ``obj`` cannot be converted with ``options`` (before any writing)."""
        if options["size"]:
            self.window(obj)

    def write(self, obj: ObjectFolder, writer: psfmt.CaptureWriter, options: dict[str, Any], progress: Progress) -> None:
        """The default conversion: the frames as stored, optionally resized to size×size."""
        size = options["size"]
        reshape = self.reshaper(obj, size)
        height, width = (size, size) if size else (obj.height, obj.width)
        writer.begin_frames(height, width, 3, np.uint16, bit_depth=16)
        for k in range(len(obj.images)):
            writer.append_frames(
                reshape(obj.image(k)),
                light_direction=obj.directions[k],
                light_intensity=obj.intensities[k],
            )
            progress((k + 1) / len(obj.images), "images")
        normal, mask = self.truth(obj, size)
        writer.set_ground_truth(psfmt.GroundTruth(normal=normal, mask=mask))

    @abstractmethod
    def window(self, obj: ObjectFolder) -> Square:
        """The square of the source image that ``--size`` resizes."""

    def reshaper(self, obj: ObjectFolder, size: int) -> Callable[[np.ndarray], np.ndarray]:
        if not size:
            return lambda image: image
        square = self.window(obj)
        return lambda image: np.clip(np.rint(area_resize(crop(image, square), size)), 0, UINT16_WHITE).astype(np.uint16)

    def truth(self, obj: ObjectFolder, size: int) -> tuple[np.ndarray | None, np.ndarray]:
        if not size:
            return obj.normal, obj.mask
        square = self.window(obj)
        normal = crop(obj.normal, square) if obj.normal is not None else None
        return resize_truth(normal, crop(obj.mask, square), size)


class DiLiGenT(_Folders):
    """DiLiGenT (``pmsData/<obj>PNG``): the 96 frames as stored, or the semi-real hybrid capture."""

    name = "diligent"
    summary = "DiLiGenT object folders: 96 frames as stored, or semi-real hybrid captures (--semi-real)"
    semi_real_options = (
        Option("event_scale", float, _SEMI.event_scale, "semi-real: event pixels per frame pixel", minimum=0.0, maximum=1.0),
        Option("sensor", str, _SEMI.sensor_model, "semi-real: sensor preset, event and frame sensor (docs/sensors.md); the options "
               "below marked 'preset' override single fields of it (None: the preset's)", choices=tuple(SENSOR_PRESETS)),
        Option("contrast", float, None, "semi-real, preset: event contrast threshold C, both polarities (log units)", minimum=0.01, maximum=5.0),
        Option("contrast_neg", float, None, "semi-real, preset: threshold C⁻ of −1 events (log units)", minimum=0.01, maximum=5.0),
        Option("contrast_sigma", float, None, "semi-real, preset: per-pixel spread σ of the thresholds", minimum=0.0, maximum=1.0),
        Option("refractory_us", float, None, "semi-real, preset: event refractory period, µs", minimum=0.0),
        Option("refractory_rule", str, None, "semi-real, preset: what an event pixel does after its refractory period (docs/sensors.md)",
               choices=REFRACTORY_RULES),
        Option("leak_hz", float, None, "semi-real, preset: leak, +1 events per pixel and second of a static pixel", minimum=0.0, maximum=MAX_NOISE_HZ),
        Option("shot_noise_hz", float, None, "semi-real, preset: shot-noise events per pixel and second in the dark", minimum=0.0,
               maximum=MAX_NOISE_HZ),
        Option("rate_spread_decades", float, None, "semi-real, preset: per-pixel spread of the noise rates, decades", minimum=0.0,
               maximum=MAX_RATE_SPREAD_DECADES),
        Option("hot_pixel_fraction", float, None, "semi-real, preset: share of hot pixels", minimum=0.0, maximum=1.0),
        Option("hot_pixel_hz", float, None, "semi-real, preset: events per second of a hot pixel", minimum=0.0, maximum=MAX_NOISE_HZ),
        Option("bit_depth", int, None, "semi-real, preset: frame bits (8, 10, 12, 16)", minimum=8, maximum=16),
        Option("black_level", float, None, "semi-real, preset: stored frame value of no light", minimum=0.0),
        Option("full_well_e", float, None, "semi-real, preset: frame electrons at saturation (shot noise; 0: none)", minimum=0.0),
        Option("read_noise_e", float, None, "semi-real, preset: frame read noise, electrons rms", minimum=0.0),
        Option("frames", int, _SEMI.frames, "semi-real: long-exposure frames per light period", minimum=1, maximum=36),
        Option("periods", int, _SEMI.periods, "semi-real: light periods to record", minimum=1, maximum=1000),
        Option("period_ms", float, _SEMI.period_ms, "semi-real: one loop of the 36 boundary lights, ms", minimum=0.0),
        Option("seed", int, _SEMI.seed, "semi-real: seed of the sensors' noise", minimum=0),
    )
    options = (
        *SELECTION_OPTIONS,
        Option("semi_real", bool, False, "write the semi-real hybrid capture (36 boundary lights as one period, frames and events)"),
        Option("discrete_lights", int, 0, "write the frame-based comparison: K of the 36 boundary lights as 8-bit instantaneous frames (0: off)",
               minimum=0, maximum=36),
        Option("size", int, 0, "frame width and height: crop a square around the mask and resize (0: full resolution, 256 for semi-real)",
               minimum=0, maximum=8192),
        *semi_real_options,
    )
    folder_suffix = "PNG"
    requires_normal = True

    def check_options(self, options: dict[str, Any]) -> None:
        if options["semi_real"] and options["discrete_lights"]:
            raise UserError("--semi-real and --discrete-lights K are two different captures: give one")
        if options["semi_real"] or options["discrete_lights"]:
            self.semi_real_config(options).check()
            return
        given = [o for o in self.semi_real_options if options[o.name] != o.default]
        if given:
            flags = ", ".join("--" + o.name.replace("_", "-") for o in given)
            raise UserError(f"{flags}: only with --semi-real or --discrete-lights")

    def check_object(self, obj: ObjectFolder, options: dict[str, Any]) -> None:
        if options["semi_real"] or options["discrete_lights"]:
            check_grid(obj)
        super().check_object(obj, options)

    @staticmethod
    def semi_real_config(options: dict[str, Any]) -> SemiRealConfig:
        contrast = options["contrast"]
        return SemiRealConfig.with_preset(
            options["sensor"],
            size=options["size"] or _SEMI.size,
            event_scale=options["event_scale"],
            contrast=contrast,
            contrast_neg=contrast if options["contrast_neg"] is None else options["contrast_neg"],
            **{name: options[name] for name in PRESET_OVERRIDES},
            frames=options["frames"],
            periods=options["periods"],
            period_ms=options["period_ms"],
            seed=options["seed"],
            discrete_lights=options["discrete_lights"],
        )

    def write(self, obj: ObjectFolder, writer: psfmt.CaptureWriter, options: dict[str, Any], progress: Progress) -> None:
        if options["semi_real"] or options["discrete_lights"]:
            write_semi_real(obj, writer, self.semi_real_config(options), progress)
        else:
            super().write(obj, writer, options, progress)

    def window(self, obj: ObjectFolder) -> Square:
        # the semi-real crop, so that resized captures line up with the semi-real ones
        return square_around(obj.mask, MARGIN_PX)


class DiLiGenTPi(_Folders):
    """DiLiGenT-Π (``DiLiGenT-Pi_release_png/<Object>``): the 100 frames as stored."""

    name = "diligent-pi"
    summary = "DiLiGenT-Π object folders: the frames as stored, ground truth when Normal_gt.mat is present"
    options = (
        *SELECTION_OPTIONS,
        Option("size", int, 0, "resize the (square) frames to N×N, e.g. 608 for half resolution (0: keep)", minimum=0, maximum=8192),
    )

    def window(self, obj: ObjectFolder) -> Square:
        if obj.height != obj.width:
            raise UserError(f"{obj.path}: --size needs square images, these are {obj.width}×{obj.height}")
        return Square(0, 0, obj.height)
