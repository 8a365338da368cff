"""Deprecated alias of ``pstoolkit._shared.worksharing``, where this module moved; it will be removed in the
release after 0.2."""

import sys

from pstoolkit._shared import worksharing as _moved

sys.modules[__name__] = _moved
