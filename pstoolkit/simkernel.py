"""Deprecated alias of ``pstoolkit.sim.ring_engine``, where this module moved; it will be removed in the
release after 0.2."""

import sys

from pstoolkit.sim import ring_engine as _moved

sys.modules[__name__] = _moved
