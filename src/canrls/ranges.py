r"""Signal ranges from the data, for the power-of-two normalisation of the regressors.

The normalisation (:attr:`canrls.model.Equation.scaling`) is chosen from signal ranges.
The DBC's min/max are the protocol's limits, often far wider than the drive ever
goes (±800 A for a 10 A servo), and the bound of a derivative column derived from
the speed range alone is the worst case of the filter; both leave the regressors
small, which costs resolution in the fixed-point kernel and lets the ridge prior
:math:`\alpha` weigh on the weakly scaled parameters. :class:`RangeScanner` measures
the ranges the filtered signals actually reach, including the filtered derivatives
(acceleration, current rate), so that the normalisation uses the data:

.. math::

    r_x = m \cdot \max_k |x_k|, \qquad
    r_{\dot\omega} = m \cdot \max_k |sF[\omega]_k|

with a headroom factor ``m`` (default 2: one bit). Signals beyond the scanned range
later are not clipped in float; in fixed point they saturate and are counted.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np

from canrls.signals import Signals
from canrls.svf import SVF

__all__ = ["RangeScanner", "scan_ranges"]


class RangeScanner:
    """Accumulates the ranges of the signals (and filtered derivatives) over blocks."""

    def __init__(self, dt: float, cutoff_hz: float, zeta: float, headroom: float = 2.0) -> None:
        self.svf = SVF(cutoff_hz, dt, zeta, ("foh", "zoh"))  # speed (sampled), current (held)
        self.headroom = float(headroom)
        self.peak: dict[str, float] = {}
        self.samples = 0

    def _put(self, key: str, v: float) -> None:
        if math.isfinite(v):
            self.peak[key] = max(self.peak.get(key, 0.0), v)

    def update(self, s: Signals) -> None:
        if len(s) == 0:
            return
        self.samples += len(s)
        for role in ("current", "speed", "voltage"):
            v = getattr(s, role)
            if v is not None:
                self._put(role, float(np.nanmax(np.abs(v))))
        _, sf = self.svf.process(np.column_stack([s.speed, s.current]))
        self._put("acceleration", float(np.nanmax(np.abs(sf[:, 0]))))
        self._put("current_rate", float(np.nanmax(np.abs(sf[:, 1]))))

    def ranges(self) -> dict[str, list[float]]:
        """``{role: [-r, r]}`` for every signal seen with a non-zero peak."""
        out = {}
        for k, v in self.peak.items():
            if v > 0:
                r = self.headroom * v
                out[k] = [-r, r]
        return out


def scan_ranges(blocks: Iterable[Signals], dt: float, cutoff_hz: float, zeta: float,
                headroom: float = 2.0) -> dict[str, list[float]]:
    """Scan blocks of samples and return their ranges (see :class:`RangeScanner`)."""
    sc = RangeScanner(dt, cutoff_hz, zeta, headroom)
    for b in blocks:
        sc.update(b)
    return sc.ranges()
