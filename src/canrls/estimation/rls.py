r"""Float recursive least squares with forgetting and a ridge prior: the reference estimator.

:class:`RLS` minimises the exponentially weighted squared error plus a ridge prior that
is forgotten like the data. The recursion runs in the C kernel
``canrls._kernels.rls_block_symmetric`` (``src/canrls/c/host/kernels_rls.h``: float64 and
float32), so per-sample :meth:`RLS.update` and block :meth:`RLS.run` give the same bits
whatever the block sizes. The cost, the symmetric and literal updates (what the literal
one costs, measured), positive definiteness, the trace bound and the noise accumulators
are in docs/architecture.md, *The float RLS*.
"""

from __future__ import annotations

import enum
import math
import operator
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from canrls import _kernels
from canrls.core.checks import check_lambda
from canrls.core.errors import CheckpointError, EstimatorError

__all__ = ["RLS", "RLSFlag", "RLSStep", "RLSTrace", "Excitation"]

FloatArray = npt.NDArray[np.floating[Any]]

#: Format tag of :meth:`RLS.state` dictionaries.
STATE_FORMAT = "canrls.rls/1"

_DTYPES = (np.dtype(np.float64), np.dtype(np.float32))

#: The block kernel of each ``RLS(update=...)`` (C, float64 or float32 by the state's
#: dtype). Arguments: ``Phi, Y, theta, P, work, acc, lam, trace_max, frozen, record,
#: eps_out, theta_out, trace_out, flags_out``; ``work`` (3, n) is scratch whose row 1
#: holds the gain of the last row, ``acc`` = [V, W]; returns the rows applied.
KERNELS = {"symmetric": _kernels.rls_block_symmetric, "literal": _kernels.rls_block_literal}


class RLSFlag(enum.IntFlag):
    """Per-step status bits of an estimator update.

    The values are part of the estimator CAN frames: never renumber them.
    """

    #: Nothing to report: a regular update.
    NONE = 0
    #: The trace bound held this step: it was taken without forgetting.
    WINDUP = 1
    #: Excitation is poor (set from :meth:`RLS.excitation`, not by the update).
    LOW_EXCITATION = 2
    #: Reserved for the fixed-point estimator: an arithmetic result saturated.
    SATURATION = 4
    #: The estimator is frozen: the error was computed, the state left untouched.
    FROZEN = 8
    #: The sample was rejected (NaN/inf in phi or y, or overflow); state untouched.
    NONFINITE = 16


# Types accepted as a scalar y without asking numpy (the per-sample path is hot).
_SCALARS = (float, int, np.floating, np.integer)

# Every combination of the bits the kernel sets, built once (IntFlag() is slow).
_FLAGS: tuple[RLSFlag, ...] = tuple(RLSFlag(i) for i in range(32))


@dataclass(frozen=True)
class RLSStep:
    r"""The result of one :meth:`RLS.update`.

    Attributes
    ----------
    eps : float
        A-priori error :math:`\varepsilon = y - \varphi^\top\theta` (before the update).
    K : ndarray, shape (n,)
        The gain applied this step (zeros when the step was not applied).
    theta : ndarray, shape (n,)
        The estimate after the step (a copy).
    trace_P : float
        :math:`\mathrm{tr}\,P` after the step.
    flags : RLSFlag
        Status bits of the step.
    """

    eps: float
    K: FloatArray
    theta: FloatArray
    trace_P: float
    flags: RLSFlag


@dataclass(frozen=True)
class RLSTrace:
    r"""The record of one :meth:`RLS.run` over a block of N samples.

    Attributes
    ----------
    eps : ndarray, shape (N,)
        A-priori errors.
    theta : ndarray, shape (N, n) or None
        Estimate after each sample; ``None`` when run with ``record=False``.
    trace_P : ndarray, shape (N,)
        :math:`\mathrm{tr}\,P` after each sample.
    flags : ndarray of uint8, shape (N,)
        :class:`RLSFlag` bits of each sample.
    theta_final : ndarray, shape (n,)
        Estimate at the end of the block (a copy).
    applied : int
        Number of samples that updated the state.
    """

    eps: FloatArray
    theta: FloatArray | None
    trace_P: FloatArray
    flags: npt.NDArray[np.uint8]
    theta_final: FloatArray
    applied: int

    def __len__(self) -> int:
        return int(self.eps.shape[0])

    def count(self, flag: RLSFlag) -> int:
        """Number of samples whose flags contain every bit of ``flag``.

        ``count(RLSFlag.NONE)`` is the number of samples without any flag.
        """
        f = int(flag)
        if f == 0:
            return int(np.count_nonzero(self.flags == 0))
        return int(np.count_nonzero((self.flags & f) == f))


@dataclass(frozen=True)
class Excitation:
    r"""How well the data excite the parameters: see :meth:`RLS.excitation`.

    Attributes
    ----------
    cond : float
        Condition number of the information matrix :math:`R = P^{-1}`
        (``inf`` if :math:`P` is not positive definite).
    min_eig, max_eig : float
        Smallest and largest eigenvalue of :math:`R` (``nan`` if :math:`P` is not
        positive definite).
    positive_definite : bool
        Whether :math:`P` is (numerically) positive definite.
    cond_max, info_min : float
        The thresholds that were applied.
    low : bool
        ``cond > cond_max`` or ``min_eig < info_min`` or :math:`P` not positive definite.
    """

    cond: float
    min_eig: float
    max_eig: float
    positive_definite: bool
    cond_max: float
    info_min: float
    low: bool

    @property
    def flags(self) -> RLSFlag:
        """``RLSFlag.LOW_EXCITATION`` when excitation is low, else ``RLSFlag.NONE``."""
        return RLSFlag.LOW_EXCITATION if self.low else RLSFlag.NONE


def check_n(n: object, who: str = "RLS") -> int:
    """The number of parameters, a positive integer, or EstimatorError naming ``who``."""
    if isinstance(n, bool):
        raise EstimatorError(f"{who} n must be a positive integer, got {n!r}")
    try:
        v = operator.index(n)  # type: ignore[arg-type]  # any object: TypeError refuses it
    except TypeError as e:
        raise EstimatorError(f"{who} n must be a positive integer, got {n!r}") from e
    if v < 1:
        raise EstimatorError(f"{who} n must be a positive integer, got {n!r}")
    return v


def check_real(name: str, value: object, who: str = "RLS") -> float:
    """``value`` as a float, or EstimatorError naming ``who`` and ``name``."""
    if isinstance(value, bool):
        raise EstimatorError(f"{who} {name} must be a real number, got {value!r}")
    try:
        return float(value)  # type: ignore[arg-type]  # any object: the errors refuse it
    except (TypeError, ValueError) as e:
        raise EstimatorError(f"{who} {name} must be a real number, got {value!r}") from e


def check_lam(lam: object, who: str = "RLS") -> float:
    """The forgetting factor (:func:`canrls.core.checks.check_lambda`), or an
    :class:`EstimatorError` naming ``who``."""
    return check_lambda(lam, f"{who} lam (forgetting factor)", EstimatorError)


def check_ridge(alpha: object, n: int, who: str = "RLS") -> npt.NDArray[np.float64]:
    r"""The ridge weights :math:`\alpha_j` as ``n`` float64 values, each finite and > 0.

    ``alpha`` is one weight for every parameter (:math:`P_0 = I/\alpha`) or one per
    parameter (:math:`P_0 = \mathrm{diag}(1/\alpha_j)`).
    """
    if isinstance(alpha, bool):
        raise EstimatorError(f"{who} alpha (ridge) must be a number, got {alpha!r}")
    try:
        a = np.array(alpha, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise EstimatorError(f"{who} alpha (ridge) must be a number, got {alpha!r}") from e
    if a.ndim == 0:
        a = np.full(n, float(a))
    if a.shape != (n,):
        raise EstimatorError(
            f"{who} alpha (ridge) must be one number or {n} numbers, got shape {a.shape}")
    if not np.all((a > 0.0) & np.isfinite(a)):
        raise EstimatorError(f"{who} alpha (ridge) must be finite and > 0, got {alpha!r}")
    return a


def ridge_value(ridge: npt.NDArray[np.float64]) -> float | npt.NDArray[np.float64]:
    """One float when every weight is the same (``alpha`` as given), else the weights."""
    return float(ridge[0]) if np.all(ridge == ridge[0]) else ridge.copy()


class RLS:
    r"""Recursive least squares with forgetting, ridge prior and windup guard.

    Parameters
    ----------
    n : int
        Number of parameters (length of :math:`\varphi`), >= 1.
    lam : float, default 1.0
        Forgetting factor :math:`\lambda \in (1/2, 1]`
        (:data:`canrls.core.checks.LAMBDA_MIN`); ``1`` keeps all data.
        In float32 the kernel uses ``lam`` rounded to float32.
    alpha : float or sequence of n floats, default 1e-3
        Ridge weight :math:`\alpha > 0`: :math:`P_0 = I/\alpha`; one weight per
        parameter gives :math:`P_0 = \mathrm{diag}(1/\alpha_j)` (the pipeline scales
        them with the data so that the prior does not depend on the normalisation).
    trace_max : float or None, default None
        Bound on :math:`\mathrm{tr}\,P`. When a step would take the trace above it,
        the step is taken with :math:`\lambda = 1` (no forgetting) and flagged
        ``WINDUP``. ``None`` means :math:`\mathrm{tr}\,P_0 = \sum_j 1/\alpha_j`: forgetting
        may bring the uncertainty back up to the prior's, never beyond it, so a
        direction that is not excited keeps the prior instead of blowing up
        (exponential windup, :math:`P \propto \lambda^{-N}`). Pass ``math.inf`` to
        disable the bound (then :math:`J_N` above is minimised exactly).
    update : {"symmetric", "literal"}, default "symmetric"
        The covariance update; ``"literal"`` only for comparison (docs/architecture.md,
        *The float RLS*).
    dtype : np.float64 or np.float32, default np.float64
        Arithmetic of the state and of the kernel. Inputs are converted to it.

    Raises
    ------
    EstimatorError
        A parameter is out of range; the message names it and its value.

    Notes
    -----
    Flags. ``WINDUP``, ``FROZEN`` and ``NONFINITE`` are set per step by the kernel.
    ``LOW_EXCITATION`` is not computed in the hot loop (it needs an eigen
    decomposition): call :meth:`excitation` at the rate you report (e.g. with each
    status frame) and OR its ``flags`` in.

    Trace bound. The decision uses the trace the step would give, computed in O(n)
    before the step; the trace summed after it may exceed ``trace_max`` by rounding
    (about n ulps), never by more. A step taken with :math:`\lambda = 1` is still an
    exact RLS step: the closed form holds with :math:`\lambda_k = 1` at those steps.

    Rejected samples. ``NONFINITE``: NaN or inf in ``phi`` or ``y``, values that
    overflow the dtype when converted (float32), or a :math:`\varphi^\top P\varphi`
    that overflows. The state is untouched and :attr:`count` (the number of applied
    updates since :meth:`reset`) does not advance; the same holds for frozen steps.

    Noise. The kernel keeps the minimised weighted cost and the weight sum,

    .. math::

        V_N = \lambda V_{N-1} + \varepsilon\, e_{post}, \quad
        e_{post} = \varepsilon\,\lambda/(\lambda + \varphi^\top P\varphi), \quad
        W_N = \lambda W_{N-1} + 1,

    where :math:`e_{post} = y - \varphi^\top\theta_{new}` is the a-posteriori error.
    :math:`V_N = J_N(\theta_N)` exactly (the product :math:`\varepsilon e_{post}`
    is the exact increment of the minimised cost; the square :math:`e_{post}^2`
    would be biased low), and :attr:`sigma2` is :math:`V_N/(W_N - n)`: for
    :math:`\lambda = 1` the classical unbiased estimate with :math:`N - n`
    degrees of freedom (plus the fading ridge term), for :math:`\lambda < 1` the
    same with :math:`W_N \to 1/(1-\lambda)` effective samples (an approximation).
    Steps held by the trace bound use :math:`\lambda = 1` here too.

    Examples
    --------
    >>> import numpy as np
    >>> rls = RLS(2, lam=0.99)
    >>> rng = np.random.default_rng(0)
    >>> Phi = rng.normal(size=(500, 2))
    >>> trace = rls.run(Phi, Phi @ np.array([2.0, -1.0]))
    >>> np.round(rls.theta, 6)
    array([ 2., -1.])
    """

    def __init__(
        self,
        n: int,
        lam: float = 1.0,
        alpha: float | npt.ArrayLike = 1e-3,
        trace_max: float | None = None,
        update: str = "symmetric",
        dtype: type[np.floating[Any]] | np.dtype[Any] | str = np.float64,
    ) -> None:
        n_int = check_n(n)
        lam_f = check_lam(lam)
        ridge = check_ridge(alpha, n_int)
        if not isinstance(update, str) or update not in KERNELS:
            raise EstimatorError(
                f"RLS update must be one of {sorted(KERNELS)}, got {update!r}"
            )
        try:
            dt = np.dtype(dtype)
        except TypeError as e:
            raise EstimatorError(f"RLS dtype must be float64 or float32, got {dtype!r}") from e
        if dt not in _DTYPES:
            raise EstimatorError(f"RLS dtype must be float64 or float32, got {dtype!r}")
        self._n = n_int
        self._ridge = ridge
        self._dtype = dt
        self._narrow = dt == np.float32  # casts into it may overflow to inf
        self._update = update
        self._kernel = KERNELS[update]
        # state
        self._theta = np.zeros(n_int, dt)
        self._P = np.zeros((n_int, n_int), dt)
        self._acc = np.zeros(2, dt)
        self._work = np.zeros((3, n_int), dt)
        self._frozen = False
        self.count = 0
        self._reset_arrays()
        #: whether the trace bound is the prior's trace (it follows a :meth:`rescale`)
        self._trace_default = trace_max is None
        if trace_max is None:
            # the prior's trace, summed in the kernel's order and dtype
            tm = _kernels.trace_of(self._P)
        else:
            tm = check_real("trace_max", trace_max)
            if not tm > 0.0:
                raise EstimatorError(f"RLS trace_max must be > 0 (or None), got {trace_max!r}")
        self._trace_max = tm
        self._trace_max_d = dt.type(tm)
        self._lam = lam_f
        self._lam_d = dt.type(lam_f)
        # buffers of the one-row block used by update()
        self._phi1 = np.zeros((1, n_int), dt)
        self._y1 = np.zeros(1, dt)
        self._eps1 = np.zeros(1, dt)
        self._tr1 = np.zeros(1, dt)
        self._flags1 = np.zeros(1, np.uint8)
        self._norec = np.zeros((0, n_int), dt)

    # ------------------------------------------------------------------ state
    def _reset_arrays(self) -> None:
        # P0 = diag(1 / alpha_j) ; theta0 = 0
        self._P[...] = 0
        self._P[np.diag_indices(self._n)] = (1.0 / self._ridge).astype(self._dtype)
        self._theta[...] = 0
        self._acc[...] = 0
        self._work[...] = 0

    @property
    def n(self) -> int:
        """Number of parameters."""
        return self._n

    @property
    def lam(self) -> float:
        r"""Forgetting factor :math:`\lambda` (change it with :meth:`set_lambda`)."""
        return self._lam

    @property
    def alpha(self) -> float | npt.NDArray[np.float64]:
        r"""Ridge weight :math:`\alpha` of the prior :math:`P_0 = I/\alpha` (one float),
        or the weights :math:`\alpha_j` of :math:`P_0 = \mathrm{diag}(1/\alpha_j)`."""
        return ridge_value(self._ridge)

    @property
    def ridge(self) -> npt.NDArray[np.float64]:
        r"""The ridge weight of every parameter, :math:`\alpha_j` (a copy)."""
        return self._ridge.copy()

    @property
    def trace_max(self) -> float:
        r"""Bound on :math:`\mathrm{tr}\,P` (``inf``: no bound)."""
        return self._trace_max

    @property
    def update_form(self) -> str:
        """``"symmetric"`` or ``"literal"``."""
        return self._update

    @property
    def dtype(self) -> np.dtype[Any]:
        """Arithmetic of the state and kernel."""
        return self._dtype

    @property
    def theta(self) -> FloatArray:
        r"""Current estimate :math:`\theta`, shape (n,) (read-only live view)."""
        v = self._theta.view()
        v.flags.writeable = False
        return v

    @property
    def P(self) -> FloatArray:
        """Current :math:`P`, shape (n, n) (read-only live view)."""
        v = self._P.view()
        v.flags.writeable = False
        return v

    @property
    def frozen(self) -> bool:
        """Whether updates currently leave the state untouched."""
        return self._frozen

    @property
    def sigma2(self) -> float:
        r"""Residual variance estimate :math:`V_N / (W_N - n)` (class Notes).

        ``nan`` until more than ``n`` (weighted) samples have been applied.
        """
        V = float(self._acc[0])
        W = float(self._acc[1])
        return V / (W - self._n) if W > self._n else math.nan

    def std(self) -> npt.NDArray[np.float64]:
        r"""Parameter standard deviations :math:`\sqrt{\hat\sigma^2\,\mathrm{diag}\,P}`.

        In the estimator's (normalised) units. Exact in the Gaussian
        :math:`\lambda = 1` case; with forgetting, :math:`\hat\sigma^2 P` is the usual
        approximation of the covariance. ``nan`` where undefined (see :attr:`sigma2`,
        or a negative diagonal of a broken literal :math:`P`).
        """
        v = self.sigma2 * np.diag(self._P).astype(np.float64)
        out = np.full(len(v), np.nan)
        return np.sqrt(v, out=out, where=v >= 0)  # NaN stays NaN (fails v >= 0)

    def reset(self) -> None:
        r"""Return to the prior :math:`P_0 = I/\alpha`, :math:`\theta_0 = 0` (count 0).

        The frozen state, ``lam`` and ``trace_max`` are kept.
        """
        self._reset_arrays()
        self.count = 0

    def freeze(self) -> None:
        r"""Stop adapting: updates compute :math:`\varepsilon` only, flagged ``FROZEN``."""
        self._frozen = True

    def resume(self) -> None:
        """Adapt again after :meth:`freeze`."""
        self._frozen = False

    def set_lambda(self, lam: float) -> None:
        """Change the forgetting factor (validated like the constructor's ``lam``)."""
        lam_f = check_lam(lam)
        self._lam = lam_f
        self._lam_d = self._dtype.type(lam_f)

    def rescale(self, d: npt.ArrayLike, dy: int = 0,
                prior: Mapping[int, float] | None = None) -> None:
        r"""New units for the columns and the output, by powers of two: column ``j``
        multiplied by :math:`2^{-d_j}`, the output by :math:`2^{-d_y}`. Then
        :math:`\theta_j \leftarrow \theta_j 2^{d_j - d_y}`,
        :math:`P_{jk} \leftarrow P_{jk} 2^{d_j + d_k}`, :math:`\alpha_j \leftarrow
        \alpha_j 2^{-2 d_j}` and the error sum :math:`\times 2^{-2 d_y}`: exact, so
        the estimate means what it meant (a prior-trace bound follows).

        ``prior`` (``{j: alpha}``) then raises the ridge weight of parameter ``j`` to
        ``alpha`` (in the new units): the difference :math:`\delta` is information
        added, :math:`P^{-1} \leftarrow P^{-1} + \delta e_j e_j^\top`, taken as one
        update with the regressor :math:`\sqrt\delta e_j` and output 0 (the prior's
        mean): :math:`g = P_{:j}/(1 + \delta P_{jj})`,
        :math:`\theta \leftarrow \theta - \delta\theta_j g`,
        :math:`P \leftarrow P - \delta g P_{j:}`.
        """
        dv = np.asarray(d, dtype=np.int64)
        if dv.shape != (self._n,):
            raise EstimatorError(f"RLS rescale needs {self._n} exponents, got {dv.shape}")
        theta = np.ldexp(self._theta.astype(np.float64), dv - int(dy))
        P = np.ldexp(self._P.astype(np.float64), dv[:, None] + dv[None, :])
        self._ridge = np.ldexp(self._ridge, -2 * dv)
        for j, alpha in (prior or {}).items():
            delta = float(alpha) - float(self._ridge[j])
            if delta > 0:
                # g = P e_j / (1 + delta P_jj)
                g = P[:, j] / (1.0 + delta * P[j, j])
                theta = theta - delta * theta[j] * g
                P = P - delta * np.outer(g, P[j, :])
                P = 0.5 * (P + P.T)
            self._ridge = self._ridge.copy()
            self._ridge[j] = float(alpha)
        self._theta[...] = theta
        self._P[...] = P
        self._acc[0] = math.ldexp(float(self._acc[0]), -2 * int(dy))
        self._prior_trace()

    def set_prior(self, j: int, alpha: float) -> None:
        r"""Give parameter ``j`` the ridge weight ``alpha`` as if from the start:
        :math:`P_{jj} \leftarrow P_{jj}\,\alpha_j/\alpha`, exact while column ``j``
        has been zero on every row (:math:`P_{jk} = 0`, :math:`\theta_j = 0`)."""
        a = check_real("alpha", alpha)
        if not (a > 0.0 and math.isfinite(a)):
            raise EstimatorError(f"RLS alpha must be > 0, got {alpha!r}")
        old = float(self._ridge[j])
        self._P[j, j] = self._P[j, j] * (old / a)
        self._ridge = self._ridge.copy()
        self._ridge[j] = a
        self._prior_trace()

    def _prior_trace(self) -> None:
        if self._trace_default:
            P0 = np.diag(1.0 / self._ridge).astype(self._dtype)
            self._trace_max = _kernels.trace_of(P0)
            self._trace_max_d = self._dtype.type(self._trace_max)

    # ----------------------------------------------------------------- update
    def update(self, phi: npt.ArrayLike, y: float) -> RLSStep:
        r"""Process one sample (a block of one row of the same kernel as :meth:`run`).

        Parameters
        ----------
        phi : array_like, shape (n,)
            Regressor :math:`\varphi`.
        y : float
            Output.

        Returns
        -------
        RLSStep
            Error, gain, estimate, trace and flags of this step.
        """
        phi_a = np.asarray(phi)
        if phi_a.shape != (self._n,):
            raise EstimatorError(f"RLS phi must have shape ({self._n},), got {phi_a.shape}")
        if not isinstance(y, _SCALARS) and np.ndim(y) != 0:
            raise EstimatorError(f"RLS y must be a scalar, got shape {np.shape(y)}")
        try:
            if self._narrow:
                with np.errstate(over="ignore"):  # out of float32 range -> inf -> rejected
                    self._phi1[0] = phi_a
                    self._y1[0] = y
            else:
                self._phi1[0] = phi_a
                self._y1[0] = y
        except (TypeError, ValueError, OverflowError) as e:
            raise EstimatorError(f"RLS phi and y must be real numbers: {e}") from e
        self.count += self._kernel(
            self._phi1, self._y1, self._theta, self._P, self._work, self._acc,
            self._lam_d, self._trace_max_d, self._frozen, False,
            self._eps1, self._norec, self._tr1, self._flags1,
        )  # fmt: skip
        return RLSStep(
            eps=float(self._eps1[0]),
            K=self._work[1].copy(),
            theta=self._theta.copy(),
            trace_P=float(self._tr1[0]),
            flags=_FLAGS[self._flags1[0]],
        )

    def run(self, Phi: npt.ArrayLike, Y: npt.ArrayLike, record: bool = True) -> RLSTrace:
        r"""Process a block of samples, carrying the state across calls.

        Parameters
        ----------
        Phi : array_like, shape (N, n)
            Regressor rows.
        Y : array_like, shape (N,)
            Targets.
        record : bool, default True
            Keep :math:`\theta` after every sample (``RLSTrace.theta``).

        Returns
        -------
        RLSTrace
            Errors, traces, flags (and estimates) per sample.
        """
        Phi_a = np.asarray(Phi)
        Y_a = np.asarray(Y)
        if Phi_a.ndim != 2 or Phi_a.shape[1] != self._n:
            raise EstimatorError(f"RLS Phi must have shape (N, {self._n}), got {Phi_a.shape}")
        N = Phi_a.shape[0]
        if Y_a.shape != (N,):
            raise EstimatorError(f"RLS Y must have shape ({N},) to match Phi, got {Y_a.shape}")
        if Phi_a.dtype == self._dtype and Y_a.dtype == self._dtype:
            # already the state's dtype: no cast, nothing can overflow
            Phi_c = np.ascontiguousarray(Phi_a)
            Y_c = np.ascontiguousarray(Y_a)
        else:
            try:
                with np.errstate(over="ignore"):  # float32: out of range -> inf -> rejected
                    Phi_c = np.ascontiguousarray(Phi_a, dtype=self._dtype)
                    Y_c = np.ascontiguousarray(Y_a, dtype=self._dtype)
            except (TypeError, ValueError, OverflowError) as e:
                raise EstimatorError(f"RLS Phi and Y must be real numbers: {e}") from e
        eps, theta, trace_P, flags, applied = self.run_block(Phi_c, Y_c, bool(record))
        return RLSTrace(
            eps=eps,
            theta=theta,
            trace_P=trace_P,
            flags=flags,
            theta_final=self._theta.copy(),
            applied=applied,
        )

    def run_block(
        self, Phi: FloatArray, Y: FloatArray, record: bool
    ) -> tuple[FloatArray, FloatArray | None, FloatArray, npt.NDArray[np.uint8], int]:
        """:meth:`run` without the checks, for a caller that built the arrays itself.

        ``Phi`` (N, n) and ``Y`` (N,) are C-contiguous float64 or state-dtype arrays.
        Returns ``(eps, theta or None, trace_P, flags, applied)`` as in :class:`RLSTrace`.
        """
        if Phi.dtype != self._dtype or Y.dtype != self._dtype:
            with np.errstate(over="ignore"):  # float32: out of range -> inf -> rejected
                Phi = Phi.astype(self._dtype)
                Y = Y.astype(self._dtype)
        N = Phi.shape[0]
        eps = np.empty(N, self._dtype)
        trace_P = np.empty(N, self._dtype)
        flags = np.empty(N, np.uint8)
        theta_out = np.empty((N, self._n), self._dtype) if record else self._norec
        applied = int(self._kernel(
            Phi, Y, self._theta, self._P, self._work, self._acc,
            self._lam_d, self._trace_max_d, self._frozen, record,
            eps, theta_out, trace_P, flags,
        ))  # fmt: skip
        self.count += applied
        return eps, (theta_out if record else None), trace_P, flags, applied

    # ------------------------------------------------------------- diagnosis
    def excitation(self, cond_max: float = 1e8, info_min: float | None = None) -> Excitation:
        r"""Measure the excitation from the information matrix :math:`R = P^{-1}`.

        :math:`R = \sum_k w_k\varphi_k\varphi_k^\top + w_0\alpha I` (weights
        :math:`w_k = \lambda^{N-k}`) includes the ridge prior. Computed on demand
        (eigenvalues of :math:`P`, O(n³)), never in the update loop.

        Parameters
        ----------
        cond_max : float, default 1e8
            Excitation is low above this condition number of :math:`R`.
        info_min : float or None, default None
            Excitation is low when the weakest direction carries less information
            than this; ``None`` means ten times the prior's information: a direction
            known barely better than from the prior alone (``10 * alpha``). (The trace
            bound keeps unexcited directions at the prior, so the condition number
            alone may stay moderate there.) With one ridge weight per parameter the
            default test and ``cond_max`` apply to the information relative to the
            prior, :math:`D^{-1/2} R D^{-1/2}` with :math:`D = \mathrm{diag}(\alpha_j)`,
            which does not depend on how the columns are scaled.

        Returns
        -------
        Excitation
        """
        cm = check_real("cond_max", cond_max)
        if not cm >= 1.0:
            raise EstimatorError(f"RLS cond_max must be >= 1, got {cond_max!r}")
        uniform = bool(np.all(self._ridge == self._ridge[0]))
        im = (10.0 * float(self._ridge.min()) if info_min is None
              else check_real("info_min", info_min))
        if not im >= 0.0:
            raise EstimatorError(f"RLS info_min must be >= 0, got {info_min!r}")
        P = self._P.astype(np.float64)
        if not np.all(np.isfinite(P)):
            return Excitation(math.inf, math.nan, math.nan, False, cm, im, True)
        # eigenvalues of P (ascending); R = P^-1 has the reciprocals
        p = np.linalg.eigvalsh(0.5 * (P + P.T))
        if not p[0] > 0.0:
            return Excitation(math.inf, math.nan, math.nan, False, cm, im, True)
        r_min = 1.0 / float(p[-1])
        r_max = 1.0 / float(p[0])
        cond = float(p[-1] / p[0])
        if uniform or info_min is not None:
            return Excitation(cond, r_min, r_max, True, cm, im, bool(cond > cm or r_min < im))
        # relative to the prior: eigenvalues of D^(1/2) P D^(1/2), D = diag(alpha_j)
        w = np.sqrt(self._ridge)
        pw = np.linalg.eigvalsh(0.5 * (P + P.T) * w[:, None] * w[None, :])
        low = bool(pw[-1] / pw[0] > cm or 1.0 / pw[-1] < 10.0)
        return Excitation(cond, r_min, r_max, True, cm, im, low)

    # ------------------------------------------------------------ checkpoint
    def state(self) -> dict[str, Any]:
        """The complete state as a plain dict (numpy arrays, numbers, strings).

        It survives ``np.savez``/``np.load``; :meth:`from_state` restores it so that
        the continuation is identical bit for bit.
        """
        return {
            "format": STATE_FORMAT,
            "n": self._n,
            "lam": self._lam,
            "alpha": ridge_value(self._ridge),
            "trace_max": self._trace_max,
            "update": self._update,
            "dtype": self._dtype.name,
            "frozen": self._frozen,
            "count": self.count,
            "theta": self._theta.copy(),
            "P": self._P.copy(),
            "acc": self._acc.copy(),
            "trace_default": self._trace_default,
        }

    @classmethod
    def from_state(cls, d: dict[str, Any] | Any) -> RLS:
        """Rebuild an estimator from :meth:`state` (also from an ``np.load`` archive).

        Raises
        ------
        CheckpointError
            A key is missing, has the wrong shape, or cannot be represented exactly.
        """

        def get(key: str) -> Any:
            try:
                value = d[key]
            except KeyError as e:
                raise CheckpointError(f"RLS checkpoint lacks key {key!r}") from e
            if isinstance(value, np.ndarray) and value.ndim == 0:
                return value.item()
            return value

        fmt = get("format")
        if fmt != STATE_FORMAT:
            raise CheckpointError(f"RLS checkpoint format is {fmt!r}, expected {STATE_FORMAT!r}")
        try:
            rls = cls(
                get("n"),
                lam=get("lam"),
                alpha=get("alpha"),
                trace_max=get("trace_max"),
                update=get("update"),
                dtype=get("dtype"),
            )
        except EstimatorError as e:
            raise CheckpointError(f"RLS checkpoint is invalid: {e}") from e
        n = rls.n
        for key, output, shape in (
            ("theta", rls._theta, (n,)),
            ("P", rls._P, (n, n)),
            ("acc", rls._acc, (2,)),
        ):
            src = np.asarray(get(key))
            if src.shape != shape:
                raise CheckpointError(
                    f"RLS checkpoint key {key!r} has shape {src.shape}, expected {shape}"
                )
            try:
                cast = src.astype(rls.dtype)
                exact = np.array_equal(cast.astype(src.dtype), src, equal_nan=True)
            except (TypeError, ValueError) as e:
                raise CheckpointError(f"RLS checkpoint key {key!r} is not numeric: {e}") from e
            if not exact:
                raise CheckpointError(
                    f"RLS checkpoint key {key!r} ({src.dtype}) is not exact in {rls.dtype}"
                )
            output[...] = cast
        count = get("count")
        if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or count < 0:
            raise CheckpointError(
                f"RLS checkpoint key 'count' must be an integer >= 0, got {count!r}"
            )
        rls._frozen = bool(get("frozen"))
        rls.count = int(count)
        rls._trace_default = bool(d.get("trace_default", False)) if hasattr(d, "get") else False
        return rls

    def __repr__(self) -> str:
        return (
            f"RLS(n={self._n}, lam={self._lam!r}, alpha={ridge_value(self._ridge)!r}, "
            f"trace_max={self._trace_max!r}, update={self._update!r}, "
            f"dtype={self._dtype.name}, count={self.count}, frozen={self._frozen})"
        )
