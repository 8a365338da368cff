"""Deprecated alias of ``pstoolkit.hardware.calibrate``, where this module moved; it will be removed in the
release after 0.2."""

import sys

from pstoolkit.hardware import calibrate as _moved

sys.modules[__name__] = _moved
