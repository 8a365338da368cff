"""Deprecated alias of ``pstoolkit.io.converter``, where this module moved; it will be removed in the
release after 0.2."""

import sys

from pstoolkit.io import converter as _moved

sys.modules[__name__] = _moved
