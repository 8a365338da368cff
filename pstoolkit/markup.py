"""Deprecated alias of ``pstoolkit.evaluation.markup``, where this module moved; it will be removed in the
release after 0.2."""

import sys

from pstoolkit.evaluation import markup as _moved

sys.modules[__name__] = _moved
