"""From physics to control: compensation and speed-loop gains from an identified model.

:mod:`~canrls.control.feedforward` (the torque the identified effects need at a position
and speed: anticogging map, harmonics, ripple), :mod:`~canrls.control.gains` (speed-loop
PI gains for a bandwidth or the symmetric optimum) and :mod:`~canrls.control.tuner` (both
for a saved model, and the files they write); :mod:`~canrls.control.tune_limits` holds the
defaults. Nothing is re-exported here, so ``canrls tune --help`` loads no numpy.
docs/tune.md.
"""
