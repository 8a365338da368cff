"""Deprecated alias of ``pstoolkit.sim.demo``, where this module moved; it will be removed in the
release after 0.2."""

import sys

from pstoolkit.sim import demo as _moved

sys.modules[__name__] = _moved
