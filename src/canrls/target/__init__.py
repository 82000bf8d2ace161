"""The whole estimator on the target: the drive's frames to parameter frames, in integers.

* :mod:`canrls.target.model` -- every integer of the per-sample path for one model and
  DBC (:func:`~canrls.target.model.build`), or the reason the target cannot run it;
* :mod:`canrls.target.spec` -- :class:`~canrls.target.spec.TargetEstimator`, the
  bit-exact specification of ``src/canrls/c/canrls_target.c``;
* :mod:`canrls.target.qmath` and :mod:`canrls.target.tables` -- its arithmetic and the
  tables of tanh, sine and 2^-x.

``docs/target.md`` describes the path, its numbers and its measurements.
"""
