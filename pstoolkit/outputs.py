"""Deprecated alias of ``pstoolkit.solve.results``, where this module moved; it will be removed in the
release after 0.2."""

import sys

from pstoolkit.solve import results as _moved

sys.modules[__name__] = _moved
