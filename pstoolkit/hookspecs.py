"""Deprecated alias of ``pstoolkit.plugin.spec``, where this module moved; it will be removed in the
release after 0.2."""

import sys

from pstoolkit.plugin import spec as _moved

sys.modules[__name__] = _moved
