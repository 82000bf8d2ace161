"""Result objects of the fixed-point RLS: one update (:class:`FixedStep`) and a run
(:class:`FixedTrace`), integers in the formats of the configuration."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from canrls.estimation.fixed.formats import FixedConfig, FixedFlag, SaturationCounts

IntArray = npt.NDArray[np.int64]
FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class FixedStep:
    """The result of one :meth:`FixedRLS.update` (integers in the config's formats).

    Attributes
    ----------
    eps : int
        A-priori error (``eps`` format).
    K : ndarray of int64, shape (n,)
        Gain applied this step, the high word of :math:`(\\tilde h\\,2^{k})(g c\\,2^{g_{up}})`:
        :math:`K\\,2^{f_h + f_g + g_{up} - 32 + e + k}` with ``e = P_exp`` before the
        renormalisation of this step and ``k`` the step's normalisation shift of
        :math:`\\tilde h` (zeros when frozen).
    theta : ndarray of int64, shape (n,)
        Estimate after the step (``theta`` format, a copy).
    trace_P : int
        :math:`\\mathrm{tr}\\,P\\,2^{f_{tr} + e}` after the step, with
        :math:`f_{tr}` = ``trace_frac``.
    P_exp : int
        Block exponent ``e`` of ``P`` after the step.
    trace_frac : int
        Fraction bits of ``trace_P`` at ``e = 0`` (``P.frac`` less the trace guard shift).
    flags : FixedFlag
        Status bits of the step.
    """

    eps: int
    K: IntArray
    theta: IntArray
    trace_P: int
    P_exp: int
    trace_frac: int
    flags: FixedFlag

    @property
    def trace_float(self) -> float:
        """:math:`\\mathrm{tr}\\,P` after the step as a float."""
        return math.ldexp(float(self.trace_P), -(self.trace_frac + self.P_exp))


@dataclass(frozen=True)
class FixedTrace:
    """The record of one :meth:`FixedRLS.run` over N samples (integers).

    Attributes
    ----------
    eps : ndarray of int64, shape (N,)
        A-priori errors (``eps`` format).
    theta : ndarray of int64, shape (N, n) or None
        Estimate after each sample (``theta`` format); ``None`` with ``record=False``.
    trace_P : ndarray of int64, shape (N,)
        :math:`\\mathrm{tr}\\,P\\,2^{f_{tr}+e}` after each sample (:meth:`trace_float`).
    P_exp : ndarray of int64, shape (N,)
        Block exponent ``e`` of ``P`` after each sample.
    trace_frac : int
        :math:`f_{tr}`: fraction bits of ``trace_P`` at ``e = 0``.
    flags : ndarray of uint8, shape (N,)
        :class:`FixedFlag` bits per sample.
    theta_final : ndarray of int64, shape (n,)
        Estimate at the end of the block.
    applied : int
        Samples that updated the state.
    saturations : SaturationCounts
        Saturations that happened during this block.
    config : FixedConfig
        The formats, to convert the integers (:meth:`theta_float`, :meth:`eps_float`).
    """

    eps: IntArray
    theta: IntArray | None
    trace_P: IntArray
    P_exp: IntArray
    trace_frac: int
    flags: npt.NDArray[np.uint8]
    theta_final: IntArray
    applied: int
    saturations: SaturationCounts
    config: FixedConfig

    def __len__(self) -> int:
        return int(self.eps.shape[0])

    def count(self, flag: FixedFlag) -> int:
        """Number of samples whose flags contain every bit of ``flag``."""
        f = int(flag)
        return int(np.count_nonzero((self.flags & f) == f))

    def theta_float(self) -> FloatArray:
        """``theta`` (or ``theta_final`` if not recorded) as floats."""
        t = self.theta if self.theta is not None else self.theta_final
        return np.asarray(self.config.theta.to_float(t))

    def eps_float(self) -> FloatArray:
        """``eps`` as floats."""
        return np.asarray(self.config.eps.to_float(self.eps))

    def trace_float(self) -> FloatArray:
        """:math:`\\mathrm{tr}\\,P` after each sample as floats."""
        return np.ldexp(self.trace_P.astype(np.float64), -(self.trace_frac + self.P_exp))


