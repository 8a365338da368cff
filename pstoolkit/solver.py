"""Deprecated alias of ``pstoolkit.solve.base``, where this module moved; it will be removed in the
release after 0.2."""

import sys

from pstoolkit.solve import base as _moved

sys.modules[__name__] = _moved
