"""Deprecated alias of ``pstoolkit.shadows.period_profile``, where this module moved; it will be removed in the
release after 0.2."""

import sys

from pstoolkit.shadows import period_profile as _moved

sys.modules[__name__] = _moved
