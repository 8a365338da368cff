"""Deprecated alias of ``pstoolkit.evaluation.metrics``, where this module moved; it will be removed in the
release after 0.2."""

import sys

from pstoolkit.evaluation import metrics as _moved

sys.modules[__name__] = _moved
