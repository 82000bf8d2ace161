r"""Fixed-point recursive least squares: the bit-exact specification of the embedded kernel.

:class:`FixedRLS` runs the recursion of :class:`canrls.estimation.rls.RLS` the way a
microcontroller runs it: integers end to end, every quantity in a signed Q format chosen
from the ranges of the problem, explicit rounding, saturation with a counter on every
store, one integer division per update. The kernel
(:func:`canrls.estimation.fixed.kernels.fixed_block`) is pure ``int64`` arithmetic, so the
same inputs give the same integers on every platform, and per-sample
:meth:`FixedRLS.update` and block :meth:`FixedRLS.run` give the same bits. The scaled
covariance, the rounding and saturation rules, the estimate and covariance in 64 bits,
the trace bound, the flags and the update forms are in docs/fixed_point.md, *The
specification in detail*.

The Q formats and the configuration are in :mod:`canrls.estimation.fixed.formats`,
the plan of shifts in :mod:`canrls.estimation.fixed.plan`, the result objects in
:mod:`canrls.estimation.fixed.trace` and the word-length sweep in
:mod:`canrls.estimation.fixed.sweep`; the package (:mod:`canrls.estimation.fixed`)
imports the names a user needs.
"""

from __future__ import annotations

import importlib
import math
from collections.abc import Mapping
from fractions import Fraction
from types import ModuleType
from typing import Any

import numpy as np
import numpy.typing as npt

from canrls.core.errors import CheckpointError, EstimatorError, FixedPointError
from canrls.estimation.fixed import layout as kernels
from canrls.estimation.fixed.formats import (
    C_FIXED,
    SITES,
    FixedConfig,
    FixedFlag,
    SaturationCounts,
    check_lam,
    check_n,
    check_real,
    check_ridge,
    nan_error,
    round_inputs,
)
from canrls.estimation.fixed.plan import build_plan
from canrls.estimation.fixed.trace import FixedStep, FixedTrace
from canrls.estimation.rls import ridge_value

IntArray = npt.NDArray[np.int64]
FloatArray = npt.NDArray[np.float64]

__all__ = ["FixedRLS"]

#: Format tag of :meth:`FixedRLS.state` dictionaries (``/3``: with ``P_frac``).
STATE_FORMAT = "canrls.fixed/3"
#: The tag before the 64-bit covariance: read with ``P_frac = 0`` (``P`` exactly its words).
STATE_FORMAT_2 = "canrls.fixed/2"
#: The tag before the 64-bit estimate: read with ``theta_frac = 0`` and ``P_frac = 0``.
STATE_FORMAT_1 = "canrls.fixed/1"
#: The range of a fraction of ``P`` (units of 2^-32 LSB): the word is ``P~`` rounded.
P_FRAC_RANGE = (-(1 << 31), (1 << 31) - 1)


_UPDATES = {
    "symmetric": kernels.MODE_SYMMETRIC,
    "literal": kernels.MODE_LITERAL,
    "naive": kernels.MODE_NAIVE,
}
_FLAGS: tuple[FixedFlag, ...] = tuple(FixedFlag(i) for i in range(16))


def _spec_kernels() -> ModuleType:
    """The compiled specification (:mod:`canrls.estimation.fixed.kernels`), imported on
    first use only: the literal and naive forms, a model larger than the C kernel's bound,
    or a machine without the extension."""
    return importlib.import_module("canrls.estimation.fixed.kernels")


# ---------------------------------------------------------------- estimator
def _int_array(name: str, x: npt.ArrayLike, shape: tuple[int, ...]) -> IntArray:
    if (type(x) is np.ndarray and x.dtype == np.int64 and x.shape == shape
            and x.flags.c_contiguous):
        return x  # the common case (quantize_inputs output), as it is
    a = np.asarray(x)
    if a.dtype == object:
        try:
            a = a.astype(np.int64)
        except (OverflowError, TypeError, ValueError) as e:
            raise EstimatorError(f"FixedRLS {name} must hold 64-bit integers: {e}") from e
    if a.dtype.kind not in "iu" or a.dtype == np.bool_:
        raise EstimatorError(
            f"FixedRLS {name} must be integers (Q format), got dtype {a.dtype}; "
            f"convert floats with quantize_inputs()"
        )
    if a.shape != shape:
        raise EstimatorError(f"FixedRLS {name} must have shape {shape}, got {a.shape}")
    if a.dtype == np.uint64 and a.size and int(a.max()) > np.iinfo(np.int64).max:
        raise EstimatorError(f"FixedRLS {name} has values beyond 64-bit signed integers")
    if a.ndim == 0:
        return np.asarray(a, dtype=np.int64)
    return np.ascontiguousarray(a, dtype=np.int64)


class FixedRLS:
    r"""Fixed-point recursive least squares (integers in, integers out).

    Parameters
    ----------
    config : FixedConfig
        Word lengths and Q formats (:meth:`FixedConfig.auto`).
    n : int
        Number of parameters.
    lam : float
        Forgetting factor, :math:`1/2 < \lambda \le 1`, stored as Q integers
        :math:`\lambda` and :math:`1/\lambda` (rounded half up, exactly).
    alpha : float or sequence of n floats
        Ridge weight: :math:`P_0 = I/\alpha`, or one per parameter,
        :math:`P_0 = \mathrm{diag}(1/\alpha_j)`; each rounded to the ``P`` format.
    trace_max : float or None, default None
        Trace bound; ``None`` is :math:`\sum_j 1/\alpha_j` (the prior's trace), ``math.inf``
        disables it.
    update : {"symmetric", "literal", "naive"}, default "symmetric"
        ``"literal"``: full-matrix :math:`P - K\varphi^\top P`; ``"naive"``: full
        matrix with :math:`\varphi^\top P` taken as :math:`(P\varphi)^\top`. Both for
        comparison only (docs/fixed_point.md, *Update forms*).

    Raises
    ------
    EstimatorError
        An argument is out of range.
    FixedPointError
        ``config`` cannot represent :math:`P_0`, :math:`\lambda` or :math:`1/\lambda`,
        or its formats leave no valid shifts (names the quantity and format).

    Examples
    --------
    >>> import numpy as np
    >>> cfg = FixedConfig.auto(n=2, alpha=1e-2, lam=0.99)
    >>> rls = FixedRLS(cfg, n=2, lam=0.99, alpha=1e-2)
    >>> rng = np.random.default_rng(0)
    >>> Phi = rng.uniform(-1, 1, size=(2000, 2))
    >>> Phi_q, Y_q, sat = rls.quantize_inputs(Phi, Phi @ np.array([0.5, -0.25]))
    >>> trace = rls.run(Phi_q, Y_q)
    >>> np.round(rls.theta_float, 6)
    array([ 0.5 , -0.25])
    """

    def __init__(
        self,
        config: FixedConfig,
        n: int,
        lam: float,
        alpha: float | npt.ArrayLike,
        trace_max: float | None = None,
        update: str = "symmetric",
    ) -> None:
        if not isinstance(config, FixedConfig):
            raise EstimatorError(f"FixedRLS config must be a FixedConfig, got {config!r}")
        n_i = check_n(n)
        lam_f = check_lam(lam)
        ridge = check_ridge(alpha, n_i)
        if update not in _UPDATES:
            raise EstimatorError(
                f"FixedRLS update must be one of {sorted(_UPDATES)}, got {update!r}"
            )
        if trace_max is None:
            tm = float(np.sum(1.0 / ridge))
        else:
            tm = check_real("trace_max", trace_max)
            if not tm > 0.0:
                raise EstimatorError(f"FixedRLS trace_max must be > 0 (or None), got {trace_max!r}")
        # P0_jj = 1/alpha_j, exactly rounded to the P format
        p0 = np.array([config.P.to_int(1 / Fraction(float(a))) for a in ridge], np.int64)
        if not np.all((p0 > 0) & (p0 <= config.P.hi)):
            raise FixedPointError(
                f"P0 = 1/alpha = {float(np.max(1.0 / ridge)):.6g} does not fit the P format "
                f"{config.P} ({config.P.bits} bit, max {config.P.max:.6g})"
            )
        self._config = config
        self._n = n_i
        self._ridge = ridge
        #: whether the trace bound is the prior's trace (it follows a :meth:`rescale`)
        self._trace_default = trace_max is None
        self._trace_max = tm
        self._update = update
        self._mode = _UPDATES[update]
        self._p0 = p0
        self._lam = lam_f
        self._plan, self._named = build_plan(config, n_i, lam_f, tm)
        self._cplan: IntArray = self._plan
        self._cplan_of: IntArray | None = None  # the plan self._cplan was built from
        self._force_spec = False
        self._trace_frac = config.P.frac - self._named["trace_ps"]
        self._in_fmt = np.array([config.phi.rounding(), config.y.rounding()])
        self._theta = np.zeros(n_i, np.int64)
        self._theta_frac = np.zeros(n_i, np.int64)  # below the LSB, 2^-32 LSB units
        self._P = np.zeros((n_i, n_i), np.int64)
        self._P_frac = np.zeros((n_i, n_i), np.int64)  # below the words, 2^-32 LSB units
        self._scale = np.zeros(2, np.int64)  # [e, c]
        self._work = np.zeros((6, n_i), np.int64)
        self._counts = np.zeros(len(SITES), np.int64)
        self._frozen = False
        self.count = 0
        self._reset_arrays()
        # one-row buffers of update()
        self._phi1 = np.zeros((1, n_i), np.int64)
        self._y1 = np.zeros(1, np.int64)
        self._eps1 = np.zeros(1, np.int64)
        self._tr1 = np.zeros(1, np.int64)
        self._exp1 = np.zeros(1, np.int64)
        self._flags1 = np.zeros(1, np.uint8)
        self._norec = np.zeros((0, n_i), np.int64)

    def _reset_arrays(self) -> None:
        # P0 = diag(1 / alpha_j) ; theta0 = 0
        self._P[...] = 0
        self._P_frac[...] = 0
        self._P[np.diag_indices(self._n)] = self._p0
        self._scale[0] = 0
        self._scale[1] = 1 << self._config.lam.frac
        self._theta[...] = 0
        self._theta_frac[...] = 0
        self._work[...] = 0

    # ----------------------------------------------------------- properties
    @property
    def config(self) -> FixedConfig:
        """Word lengths and Q formats."""
        return self._config

    @property
    def n(self) -> int:
        """Number of parameters."""
        return self._n

    @property
    def lam(self) -> float:
        """Forgetting factor (change it with :meth:`set_lambda`)."""
        return self._lam

    @property
    def alpha(self) -> float | npt.NDArray[np.float64]:
        """Ridge weight of the prior :math:`P_0 = I/\\alpha` (one float), or the weights
        :math:`\\alpha_j` of :math:`P_0 = \\mathrm{diag}(1/\\alpha_j)`."""
        return ridge_value(self._ridge)

    @property
    def trace_max(self) -> float:
        """Trace bound (``inf``: none)."""
        return self._trace_max

    @property
    def update_form(self) -> str:
        """``"symmetric"``, ``"literal"`` or ``"naive"``."""
        return self._update

    @property
    def frozen(self) -> bool:
        """Whether updates leave the state untouched."""
        return self._frozen

    @property
    def constants(self) -> dict[str, int]:
        """Every integer constant of the kernel by name (shifts, ranges, :math:`\\lambda`, ...).

        With :attr:`config` this is all an embedded implementation needs to
        reproduce the kernel bit for bit.
        """
        return dict(self._named)

    @property
    def theta(self) -> IntArray:
        """Estimate in the ``theta`` format, shape (n,) (read-only live view)."""
        v = self._theta.view()
        v.flags.writeable = False
        return v

    @property
    def theta_frac(self) -> IntArray:
        """The estimate's fraction below the LSB of :attr:`theta`, in units of
        :math:`2^{-32}` LSB (``0 <= theta_frac < 2**32``), shape (n,) (read-only live view).

        The estimate is the 64-bit ``theta * 2**32 + theta_frac``; the kernel publishes
        and predicts with the word :attr:`theta` and accumulates the updates below its
        LSB here (docs/fixed_point.md, *Rounding and saturation*).
        """
        v = self._theta_frac.view()
        v.flags.writeable = False
        return v

    @property
    def P_exp(self) -> int:
        """Block exponent ``e`` of :math:`P = c\\tilde P 2^{-(f_P + e)}`."""
        return int(self._scale[0])

    @property
    def P_scale(self) -> int:
        """Forgetting scale ``c`` of :math:`P = c\\tilde P 2^{-(f_P + e)}` (``lam`` format)."""
        return int(self._scale[1])

    @property
    def P(self) -> IntArray:
        """The words :math:`\\tilde P` of :math:`P = c\\tilde P 2^{-(f_P + e)}`, shape (n, n).

        A copy; the symmetric form's lower triangle, which the kernel never stores,
        is mirrored in. See :attr:`P_exp`, :attr:`P_scale`, :attr:`P_float`.
        """
        P = self._P.copy()
        if self._mode == kernels.MODE_SYMMETRIC:
            il = np.tril_indices(self._n, -1)
            P[il] = P.T[il]
        return P

    @property
    def P_frac(self) -> IntArray:
        """The fractions of the words :attr:`P` in units of :math:`2^{-32}` LSB, in
        :math:`[-2^{31}, 2^{31})`, shape (n, n) (a copy, mirrored like :attr:`P`).

        :math:`\\tilde P` is held in 64 bits, ``P * 2**32 + P_frac``; the word ``P`` is it
        rounded half up to the ``P`` format, which is what the kernel reads (``h = P~
        phi``, the trace); the update ``P~ - K h~'`` is subtracted from the 64 bits
        (docs/fixed_point.md, *The covariance in 64 bits*).
        """
        F = self._P_frac.copy()
        if self._mode == kernels.MODE_SYMMETRIC:
            il = np.tril_indices(self._n, -1)
            F[il] = F.T[il]
        return F

    @property
    def theta_float(self) -> FloatArray:
        """Estimate as float64 (normalised units)."""
        return np.asarray(self._config.theta.to_float(self._theta))

    @property
    def P_float(self) -> FloatArray:
        """:math:`P` as float64 (the words and their fractions), shape (n, n)."""
        c = self._config.lam.to_float(self.P_scale)
        words = self.P.astype(np.float64) + np.ldexp(self.P_frac.astype(np.float64), -32)
        return c * np.ldexp(words, -(self._config.P.frac + self.P_exp))

    @property
    def saturations(self) -> SaturationCounts:
        """Saturations per site since construction or :meth:`reset` (a snapshot)."""
        return SaturationCounts(self._counts)

    def std(self, sigma2: float) -> FloatArray:
        r"""Parameter standard deviations :math:`\sqrt{\sigma^2\,\mathrm{diag}\,P}` (float).

        Parameters
        ----------
        sigma2 : float
            Noise variance of :math:`y` in normalised units (e.g. the float
            estimator's :attr:`canrls.estimation.rls.RLS.sigma2`).

        Returns
        -------
        ndarray, shape (n,)
            ``nan`` where the diagonal of :math:`P` is negative (a broken literal P).
        """
        s2 = check_real("sigma2", sigma2)
        if not s2 >= 0.0:
            raise EstimatorError(f"FixedRLS sigma2 must be >= 0, got {sigma2!r}")
        d = np.diag(self.P_float)
        with np.errstate(invalid="ignore"):
            return np.sqrt(s2 * d)

    # -------------------------------------------------------------- control
    def reset(self) -> None:
        """Return to :math:`P_0 = I/\\alpha`, :math:`\\theta_0 = 0`; zero the counters and count.

        The frozen state, ``lam`` and ``trace_max`` are kept.
        """
        self._reset_arrays()
        self._counts[...] = 0
        self.count = 0

    def freeze(self) -> None:
        """Stop adapting: updates compute :math:`\\varepsilon` only, flagged ``FROZEN``."""
        self._frozen = True

    def resume(self) -> None:
        """Adapt again after :meth:`freeze`."""
        self._frozen = False

    def set_lambda(self, lam: float) -> None:
        """Change the forgetting factor (new Q constants; validated like the constructor's)."""
        lam_f = check_lam(lam)
        self._plan, self._named = build_plan(self._config, self._n, lam_f, self._trace_max)
        self._lam = lam_f

    def rescale(self, d: npt.ArrayLike, dy: int = 0,
                prior: Mapping[int, float] | None = None) -> None:
        r"""New units for the columns and the target, by powers of two, and raised
        priors, as :meth:`canrls.estimation.rls.RLS.rescale` does them: computed exactly
        (rationals) on the real values the words stand for, then rounded half up back to
        the words: the 64-bit estimate, and the 64-bit :math:`\tilde P` (its words and
        fractions) with the largest block exponent ``e`` (at most ``e_max``) that keeps
        :math:`\mathrm{tr}\tilde P` within half the word's range, as the kernel keeps it.
        Where even ``e = 0`` cannot hold a value it saturates, counted (``theta``, ``P``)."""
        n = self._n
        dv = [int(x) for x in np.asarray(d, dtype=np.int64).reshape(-1)]
        if len(dv) != n:
            raise EstimatorError(f"FixedRLS rescale needs {n} exponents, got {len(dv)}")
        dy = int(dy)
        cfg = self._config
        two = Fraction(2)
        # the real values: P = c P~ 2^-(f_P + e), theta = (word 2^32 + frac) 2^-(32 + f_th)
        c = Fraction(int(self._scale[1])) / two ** cfg.lam.frac
        e = int(self._scale[0])
        Pw, Pf = self.P, self.P_frac  # the whole matrix (the triangle mirrored)
        unit = c / two ** (cfg.P.frac + e + 32)
        P = [[Fraction((int(Pw[j, k]) << 32) + int(Pf[j, k])) * unit * two ** (dv[j] + dv[k])
              for k in range(n)] for j in range(n)]
        th_unit = two ** -(32 + cfg.theta.frac)
        th = [Fraction((int(self._theta[j]) << 32) | int(self._theta_frac[j])) * th_unit
              * two ** (dv[j] - dy) for j in range(n)]
        ridge = [Fraction(float(a)) / two ** (2 * x) for a, x in zip(self._ridge, dv,
                                                                     strict=True)]
        for j, alpha in (prior or {}).items():
            delta = Fraction(float(alpha)) - ridge[j]
            if delta > 0:
                # g = P e_j / (1 + delta P_jj); theta -= delta theta_j g; P -= delta g P_j.
                den = 1 + delta * P[j][j]
                g = [P[i][j] / den for i in range(n)]
                tj, Pj = th[j], list(P[j])
                th = [th[i] - delta * tj * g[i] for i in range(n)]
                P = [[P[i][k] - delta * g[i] * Pj[k] for k in range(n)] for i in range(n)]
            ridge[j] = Fraction(float(alpha))
        # theta back to its 64 bits
        q = cfg.theta
        lo, hi = q.lo << 32, (q.hi << 32) | 0xFFFFFFFF
        for j in range(n):
            v = math.floor(th[j] / th_unit + Fraction(1, 2))
            if not lo <= v <= hi:
                self._counts[kernels.S_TH] += 1
                v = min(max(v, lo), hi)
            self._theta[j], self._theta_frac[j] = v >> 32, v & 0xFFFFFFFF
        # P back to its words, with the largest block exponent that keeps them in range
        sym = self._mode == kernels.MODE_SYMMETRIC
        cells = [(j, k) for j in range(n) for k in range(j if sym else 0, n)]
        half = Fraction(1 << (cfg.P.bits - 2))
        tr = sum(P[j][j] for j in range(n))
        top = max([abs(P[j][k]) for j, k in cells] + [Fraction(0)])

        def words_at(ex: int) -> Fraction:
            return c / two ** (cfg.P.frac + ex)

        e_new = 0
        for ex in range(int(self._named["e_max"]), 0, -1):
            if tr / words_at(ex) <= half and top / words_at(ex) <= cfg.P.hi:
                e_new = ex
                break
        u = words_at(e_new) / two ** 32
        for j, k in cells:
            self._put_P(j, k, math.floor(P[j][k] / u + Fraction(1, 2)))
        self._scale[0] = e_new
        self._ridge = np.array([float(a) for a in ridge], dtype=np.float64)
        self._prior_changed()

    def set_prior(self, j: int, alpha: float) -> None:
        r"""Give parameter ``j`` the ridge weight ``alpha`` as if from the start
        (:meth:`canrls.estimation.rls.RLS.set_prior`): :math:`\tilde P_{jj} \leftarrow
        \tilde P_{jj}\,\alpha_j/\alpha` in 64 bits, rounded half up at :math:`2^{-32}` LSB,
        saturated (counted)."""
        a = check_real("alpha", alpha)
        if not (a > 0.0 and math.isfinite(a)):
            raise EstimatorError(f"FixedRLS alpha must be > 0, got {alpha!r}")
        ratio = Fraction(float(self._ridge[j])) / Fraction(a)
        V = (int(self._P[j, j]) << 32) + int(self._P_frac[j, j])
        self._put_P(j, j, math.floor(V * ratio + Fraction(1, 2)))
        self._ridge = self._ridge.copy()
        self._ridge[j] = a
        self._prior_changed()

    def _put_P(self, j: int, k: int, V: int) -> None:
        r"""Store :math:`V = \tilde P_{jk} 2^{32}` as the word ``rsh(V, 32)`` and its
        fraction, saturated to the word (counted), as the kernel stores it."""
        P = self._config.P
        lo, hi = (P.lo << 32) - (1 << 31), (P.hi << 32) + (1 << 31) - 1
        if not lo <= V <= hi:
            self._counts[kernels.S_P] += 1
            V = min(max(V, lo), hi)
        w = (V + (1 << 31)) >> 32
        self._P[j, k], self._P_frac[j, k] = w, V - (w << 32)

    def _prior_changed(self) -> None:
        """The prior's words for :meth:`reset` and, where it is the prior's, the trace bound."""
        P = self._config.P
        self._p0 = np.array([min(max(P.to_int(1 / Fraction(float(a))), 1), P.hi)
                             for a in self._ridge], np.int64)
        if self._trace_default:
            self._trace_max = float(np.sum(1.0 / self._ridge))
            self._plan, self._named = build_plan(self._config, self._n, self._lam,
                                                  self._trace_max)

    # -------------------------------------------------------------- updates
    def quantize_inputs(
        self, Phi: npt.ArrayLike, Y: npt.ArrayLike, count: bool = True
    ) -> tuple[IntArray, IntArray, SaturationCounts]:
        """Round normalised float inputs to the input formats (:meth:`FixedConfig.quantize_inputs`).

        Parameters
        ----------
        Phi : array_like, shape (N, n) (or (n,))
        Y : array_like, shape (N,) (or scalar)
        count : bool, default True
            Add the input saturations to this estimator's ``phi_in``/``y_in``
            counters (the values handed to :meth:`run` are then in range, so the
            kernel does not count them again).

        Returns
        -------
        (Phi_int, Y_int, saturations)
        """
        Pq, Yq, sat = self._config.quantize_inputs(Phi, Y)
        if Pq.ndim not in (1, 2) or Pq.shape[-1] != self._n:
            raise EstimatorError(f"FixedRLS Phi must have shape (N, {self._n}), got {Pq.shape}")
        if count:
            self._counts[kernels.S_PHI] += sat["phi_in"]
            self._counts[kernels.S_Y] += sat["y_in"]
        return Pq, Yq, sat

    def quantize_block(self, Phi: FloatArray, Y: FloatArray) -> tuple[IntArray, IntArray]:
        """:meth:`quantize_inputs` (counted) without the checks, for a caller that built
        ``Phi`` (N, n) and ``Y`` (N,) itself, C-contiguous float64."""
        Pq = np.empty(Phi.shape, np.int64)
        Yq = np.empty(Y.shape, np.int64)
        nan = round_inputs(Phi.reshape(-1), Y, self._in_fmt, Pq.reshape(-1), Yq, self._counts)
        if nan:
            raise nan_error(self._config.phi if nan == 1 else self._config.y)
        return Pq, Yq

    def update(self, phi_int: npt.ArrayLike, y_int: int) -> FixedStep:
        r"""Process one sample: a block of one row of the same kernel as :meth:`run`.

        Parameters
        ----------
        phi_int : array_like of int, shape (n,)
            Regressor in the ``phi`` format (clamped to it if outside, counted).
        y_int : int
            Target in the ``y`` format.

        Returns
        -------
        FixedStep
        """
        if (
            type(phi_int) is np.ndarray
            and phi_int.dtype == np.int64
            and phi_int.shape == (self._n,)
        ):
            self._phi1[0] = phi_int  # the common case, without conversions
        else:
            self._phi1[0] = _int_array("phi_int", phi_int, (self._n,))
        if type(y_int) is int and -(1 << 63) <= y_int < (1 << 63):
            self._y1[0] = y_int
        else:
            self._y1[0] = _int_array("y_int", y_int, ())
        self.count += self._block(
            self._phi1, self._y1, False, self._eps1, self._norec, self._tr1, self._exp1,
            self._flags1,
        )  # fmt: skip
        return FixedStep(
            eps=int(self._eps1[0]),
            K=self._work[4].copy(),
            theta=self._theta.copy(),
            trace_P=int(self._tr1[0]),
            P_exp=int(self._exp1[0]),
            trace_frac=self._trace_frac,
            flags=_FLAGS[self._flags1[0]],
        )

    def run(self, Phi_int: npt.ArrayLike, Y_int: npt.ArrayLike, record: bool = True) -> FixedTrace:
        r"""Process a block of samples with the compiled kernel, carrying the state.

        Parameters
        ----------
        Phi_int : array_like of int, shape (N, n)
            Regressor rows in the ``phi`` format.
        Y_int : array_like of int, shape (N,)
            Targets in the ``y`` format.
        record : bool, default True
            Keep :math:`\theta` after every sample.

        Returns
        -------
        FixedTrace
        """
        Phi_a = np.asarray(Phi_int)
        if Phi_a.ndim != 2 or Phi_a.shape[1] != self._n:
            raise EstimatorError(
                f"FixedRLS Phi_int must have shape (N, {self._n}), got {Phi_a.shape}"
            )
        N = Phi_a.shape[0]
        Phi_c = _int_array("Phi_int", Phi_a, (N, self._n))
        Y_c = _int_array("Y_int", Y_int, (N,))
        before = self._counts.copy()
        eps, theta, trace_P, P_exp, flags, applied = self.run_block(Phi_c, Y_c, bool(record))
        return FixedTrace(
            eps=eps,
            theta=theta,
            trace_P=trace_P,
            P_exp=P_exp,
            trace_frac=self._trace_frac,
            flags=flags,
            theta_final=self._theta.copy(),
            applied=applied,
            saturations=SaturationCounts(self._counts - before),
            config=self._config,
        )

    def run_block(
        self, Phi_int: IntArray, Y_int: IntArray, record: bool
    ) -> tuple[IntArray, IntArray | None, IntArray, IntArray, npt.NDArray[np.uint8], int]:
        """:meth:`run` without the checks, for a caller that built the arrays itself.

        ``Phi_int`` (N, n) and ``Y_int`` (N,) are C-contiguous ``int64``. Returns
        ``(eps, theta or None, trace_P, P_exp, flags, applied)`` as in :class:`FixedTrace`.
        """
        N = Phi_int.shape[0]
        eps = np.empty(N, np.int64)
        trace_P = np.empty(N, np.int64)
        P_exp = np.empty(N, np.int64)
        flags = np.empty(N, np.uint8)
        theta_out = np.empty((N, self._n), np.int64) if record else self._norec
        applied = self._block(Phi_int, Y_int, record, eps, theta_out, trace_P, P_exp, flags)
        self.count += applied
        return eps, (theta_out if record else None), trace_P, P_exp, flags, applied

    @property
    def backend(self) -> str:
        """``"c"``: the blocks run in the C kernel (``canrls._fixed``, the symmetric form
        with ``n <= N_MAX``); ``"spec"``: in the compiled specification
        (:func:`canrls.estimation.fixed.kernels.fixed_block`). Both give the same integers.

        Set it to ``"spec"`` to run the specification (a test's reference), or to
        ``"auto"`` for the C kernel wherever it applies (the default).
        """
        if (not self._force_spec and C_FIXED is not None
                and self._mode == kernels.MODE_SYMMETRIC and self._n <= C_FIXED.N_MAX):
            return "c"
        return "spec"

    @backend.setter
    def backend(self, value: str) -> None:
        if value not in ("spec", "auto"):
            raise EstimatorError(f"FixedRLS backend must be 'spec' or 'auto', got {value!r}")
        self._force_spec = value == "spec"

    def _block(self, Phi: IntArray, Y: IntArray, record: bool, eps: IntArray,
               theta_out: IntArray, trace_P: IntArray, P_exp: IntArray,
               flags: npt.NDArray[np.uint8]) -> int:
        """Run the kernel (:attr:`backend`) over a block, in place; rows applied."""
        if self.backend == "c":
            assert C_FIXED is not None
            if self._cplan_of is not self._plan:
                # the plan in the order of the C struct's fields (canrls_plan_q31)
                self._cplan = np.array([self._named[f] for f in C_FIXED.PLAN_FIELDS], np.int64)
                self._cplan_of = self._plan
            return int(C_FIXED.run_block(
                Phi, Y, self._theta, self._theta_frac, self._P, self._P_frac, self._scale,
                self._work[4], self._counts, self._cplan, self._frozen, eps,
                theta_out if record else None, trace_P, P_exp, flags,
            ))  # fmt: skip
        return int(_spec_kernels().fixed_block(
            Phi, Y, self._theta, self._theta_frac, self._P, self._P_frac, self._scale,
            self._work, self._counts, self._plan, self._mode, self._frozen, record,
            eps, theta_out, trace_P, P_exp, flags,
        ))  # fmt: skip

    # ----------------------------------------------------------- checkpoint
    def state(self) -> dict[str, Any]:
        """The complete state as a plain dict (ints, strings, int64 arrays).

        Survives ``np.savez``/``np.load`` and JSON (after ``.tolist()``);
        :meth:`from_state` continues bit for bit.
        """
        return {
            "format": STATE_FORMAT,
            "config": self._config.to_dict(),
            "n": self._n,
            "lam": self._lam,
            "alpha": ridge_value(self._ridge),
            "trace_max": self._trace_max,
            "update": self._update,
            "frozen": self._frozen,
            "count": self.count,
            "theta": self._theta.copy(),
            "theta_frac": self._theta_frac.copy(),
            "P": self._P.copy(),
            "P_frac": self._P_frac.copy(),
            "P_exp": int(self._scale[0]),
            "P_scale": int(self._scale[1]),
            "counts": self._counts.copy(),
            "trace_default": self._trace_default,
        }

    @classmethod
    def from_state(cls, d: Mapping[str, Any] | Any) -> FixedRLS:
        """Rebuild an estimator from :meth:`state`.

        Raises
        ------
        CheckpointError
            A key is missing or malformed, or a value lies outside its word.
        """

        def get(key: str) -> Any:
            try:
                v = d[key]
            except KeyError as e:
                raise CheckpointError(f"FixedRLS checkpoint lacks key {key!r}") from e
            if isinstance(v, np.ndarray) and v.ndim == 0:
                return v.item()
            return v

        fmt = get("format")
        if fmt not in (STATE_FORMAT, STATE_FORMAT_2, STATE_FORMAT_1):
            raise CheckpointError(
                f"FixedRLS checkpoint format is {fmt!r}, expected {STATE_FORMAT!r} "
                f"(or {STATE_FORMAT_2!r}, read with P_frac = 0, or {STATE_FORMAT_1!r}, "
                f"read with theta_frac = 0 and P_frac = 0)"
            )
        try:
            cfg_d = get("config")
            if isinstance(cfg_d, str):
                import json

                cfg_d = json.loads(cfg_d)
            rls = cls(
                FixedConfig.from_dict(cfg_d),
                get("n"),
                lam=get("lam"),
                alpha=get("alpha"),
                trace_max=get("trace_max"),
                update=get("update"),
            )
        except (EstimatorError, TypeError, ValueError) as e:
            raise CheckpointError(f"FixedRLS checkpoint is invalid: {e}") from e
        n = rls.n
        cfg = rls.config
        frac = (0, (1 << 32) - 1)  # theta_frac: 2^-32 LSB, below one LSB
        for key, target, shape, q in (
            ("theta", rls._theta, (n,), cfg.theta),
            *((("theta_frac", rls._theta_frac, (n,), frac),) if fmt != STATE_FORMAT_1 else ()),
            ("P", rls._P, (n, n), cfg.P),
            *((("P_frac", rls._P_frac, (n, n), P_FRAC_RANGE),) if fmt == STATE_FORMAT else ()),
            ("counts", rls._counts, (len(SITES),), None),
        ):
            try:
                src = _int_array(key, get(key), shape)
            except EstimatorError as e:
                raise CheckpointError(f"FixedRLS checkpoint key {key!r}: {e}") from e
            lo, hi = (
                (0, np.iinfo(np.int64).max) if q is None
                else q if isinstance(q, tuple) else (q.lo, q.hi)
            )
            if src.size and (int(src.min()) < lo or int(src.max()) > hi):
                raise CheckpointError(
                    f"FixedRLS checkpoint key {key!r} has values outside [{lo}, {hi}]"
                )
            target[...] = src
        p_exp = get("P_exp")
        if (
            isinstance(p_exp, bool)
            or not isinstance(p_exp, int | np.integer)
            or not (0 <= int(p_exp) <= rls._named["e_max"])
        ):
            raise CheckpointError(
                f"FixedRLS checkpoint key 'P_exp' = {p_exp!r} is not an integer in "
                f"0..{rls._named['e_max']}"
            )
        c = get("P_scale")
        if (
            isinstance(c, bool)
            or not isinstance(c, int | np.integer)
            or not (0 < int(c) <= rls._named["one_lam"])
        ):
            raise CheckpointError(
                f"FixedRLS checkpoint key 'P_scale' = {c!r} is not an integer in "
                f"1..{rls._named['one_lam']}"
            )
        rls._scale[0] = int(p_exp)
        rls._scale[1] = int(c)
        rls._frozen = bool(get("frozen"))
        rls.count = int(get("count"))
        rls._trace_default = bool(d.get("trace_default", False)) if hasattr(d, "get") else False
        return rls

    def __repr__(self) -> str:
        return (
            f"FixedRLS({self._config.label}, n={self._n}, lam={self._lam!r}, "
            f"alpha={ridge_value(self._ridge)!r}, trace_max={self._trace_max!r}, "
            f"update={self._update!r}, "
            f"count={self.count}, frozen={self._frozen})"
        )


