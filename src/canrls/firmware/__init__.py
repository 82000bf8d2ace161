"""The export for the target (``canrls export-c``): the drive's frames to parameter frames,
in integers, and the C a firmware team compiles.

* :mod:`canrls.firmware.kernel_export` -- the fixed-point kernel's C and a model's
  configuration of it (:func:`~canrls.firmware.kernel_export.export_c`);
* :mod:`canrls.firmware.target_export` -- the whole estimator's files, README and tests;
* :mod:`canrls.firmware.cgen` and :mod:`canrls.firmware.vectors` -- the model's constant
  in C and test vectors from logs;
* :mod:`canrls.firmware.target_model` -- every integer of the per-sample path for one model and
  DBC (:func:`~canrls.firmware.target_model.build`), or the reason the target cannot run it;
* :mod:`canrls.firmware.spec` -- :class:`~canrls.firmware.spec.TargetEstimator`, the
  bit-exact specification of ``src/canrls/c/firmware/canrls_target.c``;
* :mod:`canrls.firmware.qmath` and :mod:`canrls.firmware.tables` -- its arithmetic and the
  tables of tanh, sine and 2^-x.

* :mod:`canrls.firmware.target_fit`, :mod:`canrls.firmware.load` and
  :mod:`canrls.firmware.target_live` -- the fixed column of ``canrls fit`` and of the daemon:
  the frames through the specification.

Its C is in ``src/canrls/c/firmware``; ``docs/target.md`` describes the path, its numbers
and its measurements.
"""
