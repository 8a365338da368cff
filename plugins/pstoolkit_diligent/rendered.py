"""The semi-real recipe on a rendered shape: a classic capture under DiLiGenT's 96 grid lights goes
through the same files and code as a real DiLiGenT object.

    pstoolkit simulate geometry --source bear --lights grid --bit-depth 16 --auto-gain peak -o bear96.h5
    semi_real_from_capture(Path("bear96.h5"), Path("bear-semi.h5"), refractory_us=2000.0)

is the command chain ``pstoolkit export bear96.h5 --frames diligent -o bearPNG`` followed by
``pstoolkit convert diligent bearPNG --semi-real -o bear-semi.h5``, with the folder kept in a
temporary place beside the output and removed afterwards.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

from pstoolkit import Progress, UserError, no_progress
from pstoolkit.io.diligent_export import export_diligent
from pstoolkit.plugin.options import defaults
from pstoolkit_diligent.converters import DiLiGenT

SELECTION = ("object", "all", "semi_real")
"""Options of ``convert diligent`` that name what to convert rather than how: not settings here."""
EXPORT_SHARE = 0.2


def semi_real_from_capture(capture: Path, out: Path, progress: Progress = no_progress, **settings: Any) -> Path:
    """Write the semi-real hybrid capture ``out`` of the classic 96-light grid capture ``capture``
    (``pstoolkit simulate --lights grid`` or ``--lights light_directions.txt`` of DiLiGenT's rig).

    ``settings`` are ``convert diligent`` options by name (``size``, ``event_scale``, ``contrast``,
    ``refractory_us``, ``frames``, ``periods``, ``period_ms``, ``seed``, …, checked like the
    command's); ``discrete_lights=K`` writes the frame-based comparison instead. The capture needs
    ground-truth normals (the converter's ``Normal_gt.mat``). UserError for a bad setting, a capture
    that is not a classic one or has another number of lights than 96. Returns ``out``."""
    known = {o.name: o for o in DiLiGenT.options if o.name not in SELECTION}
    options = defaults(DiLiGenT.options)
    for name, value in settings.items():
        if name not in known:
            raise UserError(f"semi_real_from_capture: no setting {name!r} (settings: {', '.join(sorted(known))})")
        options[name] = known[name].check(value)
    options["semi_real"] = not options["discrete_lights"]
    if not out.parent.is_dir():
        raise UserError(f"{out}: folder {out.parent} does not exist")
    with tempfile.TemporaryDirectory(dir=out.parent, prefix=f".{out.name}.") as staging:
        folder = Path(staging) / f"{capture.stem}PNG"
        export_diligent(capture, folder, progress=lambda f, m: progress(EXPORT_SHARE * f, m))
        DiLiGenT().convert(folder, out, options, lambda f, m: progress(EXPORT_SHARE + (1.0 - EXPORT_SHARE) * f, m))
    return out
