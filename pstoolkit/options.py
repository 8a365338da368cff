"""Deprecated alias of ``pstoolkit.plugin.options``, where this module moved; it will be removed in the
release after 0.2."""

import sys

from pstoolkit.plugin import options as _moved

sys.modules[__name__] = _moved
