"""Cast-shadow detection: the registry kind ``shadow detectors`` and the built-in ones.

A detector turns ``ShadowEvidence`` (the events of one light period at the event pixels, the
exposures, the light, the sensor and, once a solver has one, its surface estimate) into a
``ShadowMask`` — the cast-shadow mask m_c(x, t) of DualResPS eq. 14 at frame pixels, as intervals of
the light's phase. Built in (registered by the ``core`` plugin):

- ``none``: no mask (the ablation);
- ``spikes``: Algorithm 1 of the DualResPS supplement on the event interval profile (eq. 20); it sees
  shadow edges as bursts, which a refractory period longer than about 0.3 ms (at C = 0.15) hides;
- ``silences``: dark spans of the event polarity pattern, for any refractory period and rule;
- ``geometry``: shadows of the solver's surface, integrated and ray-marched;
- ``fused``: ``geometry`` confirmed by the dark spans of ``silences`` or, where light fills a shadow,
  by the events' fall and rise at its edges (``edge_seen``); dualres's default.

``pstoolkit.shadows.score`` rates a mask against the truth of a simulated capture. This package
imports neither torch nor numba; the sweeps load them when first used.
"""

from __future__ import annotations

from pstoolkit.shadows.base import NoShadows, ShadowDetector, ShadowEvidence, ShadowMask
from pstoolkit.shadows.intervals import ShadowIntervals, ShadowTable
from pstoolkit.shadows.period_profile import Profile, interval_profile

__all__ = [
    "NoShadows",
    "Profile",
    "ShadowDetector",
    "ShadowEvidence",
    "ShadowIntervals",
    "ShadowMask",
    "ShadowTable",
    "interval_profile",
]
