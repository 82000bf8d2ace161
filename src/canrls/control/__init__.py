"""From physics to control: compensation and speed-loop gains from an identified model.

:mod:`~canrls.control.feedforward` (the torque the identified effects need at a position
and speed: anticogging map, harmonics, ripple) and :mod:`~canrls.control.gains` (speed-loop
PI gains for a bandwidth or the symmetric optimum); :mod:`~canrls.control.tune` puts them
together for a saved model. docs/tune.md.
"""

from canrls.control.feedforward import Feedforward, Harmonic, Ripple, Term, feedforward
from canrls.control.gains import Loop, SpeedGains, for_bandwidth, symmetric_optimum

__all__ = ["Feedforward", "Harmonic", "Ripple", "Term", "feedforward", "Loop", "SpeedGains",
           "for_bandwidth", "symmetric_optimum"]
