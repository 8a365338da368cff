"""Deprecated alias of ``pstoolkit.optics.brdf``, where this module moved; it will be removed in the
release after 0.2."""

import sys

from pstoolkit.optics import brdf as _moved

sys.modules[__name__] = _moved
