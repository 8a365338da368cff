"""Deprecated alias of ``pstoolkit.io.diligent_export``, where this module moved; it will be removed in the
release after 0.2."""

import sys

from pstoolkit.io import diligent_export as _moved

sys.modules[__name__] = _moved
