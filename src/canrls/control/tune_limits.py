"""The defaults and limits of ``canrls tune``, in one place (no numpy: ``--help`` reads them)."""

from __future__ import annotations

__all__ = ["MAX_POINTS", "DEFAULT_POINTS", "DEFAULT_SHARE", "DEFAULT_MARGIN", "DEFAULT_DELAY"]

#: Most points of an anticogging map per revolution (pitch): a 16-bit index.
MAX_POINTS = 65536
#: Points of the map unless asked.
DEFAULT_POINTS = 1024
#: Default largest sigma, as a share of a term's size, of a term that is compensated.
DEFAULT_SHARE = 0.2
#: Phase margin of a speed loop tuned for a bandwidth unless stated [deg].
DEFAULT_MARGIN = 60.0
#: Delay of the speed loop in control periods unless stated: one period of computation
#: and half a period of the hold.
DEFAULT_DELAY = 1.5
