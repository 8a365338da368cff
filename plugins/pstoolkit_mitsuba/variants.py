"""Which Mitsuba variant renders: ``scalar_rgb`` (one ray at a time, needs nothing) or
``llvm_ad_rgb`` (vectorised, JIT-compiled through LLVM).

``llvm_ad_rgb`` aborts the whole process ("Cannot select fmaximum") with Debian 12's default LLVM
(14/15) and works with ``libllvm19``; an abort cannot be caught, so ``auto`` picks it only when
``DRJIT_LIBLLVM_PATH`` names an LLVM library and a tiny render in a child process succeeds with it,
and falls back to ``scalar_rgb`` otherwise. The probe's answer is kept for the process.
"""

from __future__ import annotations

import os
import subprocess
import sys
from functools import cache

from pstoolkit import UserError

SCALAR, LLVM = "scalar_rgb", "llvm_ad_rgb"
AUTO = "auto"
VARIANTS = (AUTO, SCALAR, LLVM)
LLVM_PATH = "DRJIT_LIBLLVM_PATH"
PROBE_TIMEOUT_S = 120.0

_PROBE = """
import mitsuba as mi
mi.set_variant("llvm_ad_rgb")
scene = mi.load_dict({"type": "scene", "integrator": {"type": "path"}, "shape": {"type": "sphere"}, "light": {"type": "constant"},
                      "sensor": {"type": "perspective", "film": {"type": "hdrfilm", "width": 4, "height": 4}}})
print(float(mi.render(scene, spp=4).numpy().mean()))
"""


@cache
def llvm_works() -> bool:
    """Whether ``llvm_ad_rgb`` renders in a child process with the LLVM of ``DRJIT_LIBLLVM_PATH``
    (False when the variable is unset: Dr.Jit's default search finds Debian's LLVM, which aborts)."""
    path = os.environ.get(LLVM_PATH, "")
    if not path or not os.path.isfile(path):
        return False
    try:
        done = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, timeout=PROBE_TIMEOUT_S, check=False)
    except (OSError, subprocess.TimeoutExpired):
        return False
    return done.returncode == 0


def choose_variant(name: str) -> str:
    """The variant to render with for the option value ``name`` (``VARIANTS``): ``auto`` is
    ``llvm_ad_rgb`` when ``llvm_works()``, else ``scalar_rgb``; ``llvm_ad_rgb`` asked for by name
    without a working LLVM is a UserError rather than an abort."""
    if name == AUTO:
        return LLVM if llvm_works() else SCALAR
    if name == LLVM and not llvm_works():
        raise UserError(f"variant {LLVM} needs {LLVM_PATH} set to a working LLVM library (Debian: apt-get install libllvm19; "
                        f"{LLVM_PATH}=/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1); variant {SCALAR} needs nothing")
    return name


def set_variant(name: str):  # noqa: ANN201 -- the mitsuba module, typed by mitsuba itself
    """Import mitsuba with the variant ``choose_variant(name)`` set, and return the module."""
    import mitsuba as mi

    mi.set_variant(choose_variant(name))
    return mi
