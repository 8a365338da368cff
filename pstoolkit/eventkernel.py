"""Deprecated alias of ``pstoolkit.events.relation_kernel``, where this module moved; it will be removed in the
release after 0.2."""

import sys

from pstoolkit.events import relation_kernel as _moved

sys.modules[__name__] = _moved
