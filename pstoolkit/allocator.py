"""Deprecated alias of ``pstoolkit._shared.allocator``, where this module moved; it will be removed in the
release after 0.2."""

import sys

from pstoolkit._shared import allocator as _moved

sys.modules[__name__] = _moved
