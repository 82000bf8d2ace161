"""Fixed-point recursive least squares: the bit-exact specification of the target's kernel.

The modules, lowest first: ``layout`` (the C kernel's enums and sites), ``formats`` (Q
formats, :class:`FixedConfig`, :class:`SaturationCounts`), ``kernels`` (the integer
arithmetic, in C or in Python), ``plan`` (the shifts of one update), ``trace`` (per-step
and per-run results), ``estimator`` (:class:`FixedRLS`) and ``sweep`` (the word-length
sweep of ``canrls fixed-sweep``). The names a user needs are imported here.
"""

from canrls.estimation.fixed.estimator import FixedRLS
from canrls.estimation.fixed.formats import (
    SITES,
    FixedConfig,
    FixedFlag,
    QFormat,
    SaturationCounts,
)
from canrls.estimation.fixed.trace import FixedStep, FixedTrace

__all__ = ["QFormat", "FixedConfig", "FixedFlag", "SaturationCounts", "FixedStep",
           "FixedTrace", "FixedRLS", "SITES"]
