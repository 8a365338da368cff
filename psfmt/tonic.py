"""Deprecated alias of ``psfmt.structured``, where this module moved; it will be removed in the
release after 0.2."""

import sys

from psfmt import structured as _moved

sys.modules[__name__] = _moved
