r"""The pure pipeline: samples -> regressors -> float and fixed RLS -> estimates.

:class:`Pipeline` is shared by the live daemon (``canrls run``) and the offline replay
(``canrls fit``, ``canrls diagnose``). It takes :class:`~canrls.core.samples.Signals`
blocks of any size and carries every state across them, sample by sample in the C
kernels of ``canrls._kernels`` (``src/canrls/c/host/kernels.c``) and in the fixed-point
kernels, so the same samples give the same parameters bit for bit whatever the block
sizes (the replay reads 64 k frames at a time, the daemon whatever has arrived).

Per equation of the model (mechanical, and electrical when present):

1. the :class:`~canrls.estimation.model.RegressorBuilder` filters output and columns with the
   state-variable filter and normalises them by powers of two;
2. samples inside the filter's warm-up (after the start, a reset or a gap in the
   sample times) are not used: the filter's zero initial state does not match the
   signals there, so the filtered equation does not hold yet (short gaps are filled;
   :class:`~canrls.estimation.selection.SamplePolicy` decides, for the diagnosis too);
3. the float reference :class:`~canrls.estimation.rls.RLS` and the fixed-point
   :class:`~canrls.estimation.fixed.estimator.FixedRLS` (inputs quantised at the
   boundary) update on the same rows;
4. the sufficient statistics (``sum phi phi'``, ``sum phi y``, ``sum y^2``) accumulate,
   so that the residual of the final estimate over all data, the fit and
   :math:`R^2` come without a second pass, in memory independent of the log length.

Goodness of fit, as MATLAB's ``compare``:

.. math::

    \mathrm{fit} = 100\,\Big(1 - \frac{\lVert y - \Phi\hat\theta\rVert}
                                    {\lVert y - \bar y\rVert}\Big), \qquad
    R^2 = 1 - \frac{\lVert y - \Phi\hat\theta\rVert^2}{\lVert y - \bar y\rVert^2}

computed on the filtered output, in the output's unit.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Any, cast

import numpy as np
import numpy.typing as npt

from canrls import _kernels
from canrls.core.background import Background
from canrls.core.errors import ConfigError
from canrls.core.samples import Signals
from canrls.estimation.equation import Equation, RegressorBuilder
from canrls.estimation.estimates import (
    EquationBlock,
    EquationFit,
    Estimates,
    ParameterEstimate,
    PipelineBlock,
    Rescale,
    divergence,
)
from canrls.estimation.fixed.estimator import FixedRLS
from canrls.estimation.fixed.formats import SaturationCounts
from canrls.estimation.model import OLD_OUTPUT_KEY, Model
from canrls.estimation.rls import RLS
from canrls.estimation.selection import SamplePolicy, SampleSelector
from canrls.estimation.settings import (
    RESCALE_HEADROOM,
    RESCALE_LIMIT,
    RMS_HEADROOM,
    EstimatorSettings,
    exponent_for,
)
from canrls.estimation.sigma_inflation import ResidualTail, prior_share

__all__ = ["EquationEstimator", "Pipeline"]

F64 = npt.NDArray[np.float64]

#: At most this many rescales are listed (:attr:`EquationEstimator.rescales`; all counted).
MAX_RESCALES_LISTED = 64


#: The check filter's cutoff, a fraction of the model's (:meth:`EquationEstimator.bias`).
CHECK_CUTOFF = 0.5
#: The bias bound is this many times the difference of the two filters' estimates: a
#: bias that falls like the cutoff (or faster) is at most twice the difference.
CHECK_FACTOR = 2.0
#: Blocks of at least this many used rows run the fixed-point estimator in a thread
#: beside the float one (the offline replay's blocks; the daemon's, some 200 rows, stay
#: in one thread, where a hand-over would cost more than the overlap saves).
OVERLAP_ROWS = 4096


# ----------------------------------------------------------------------- estimator
def _noise_explains(A: F64, B: F64, share: float = 1.0) -> npt.NDArray[np.bool_]:
    r"""Which parameters a combination of columns involves whose energy in ``A`` the
    noise (energy ``B``) could account for, at least ``share`` of it (1: all of it; the
    white noise model overstates an encoder's differenced speed noise, so no less):
    the generalised eigenvectors of
    :math:`B x = \mu A x` with :math:`\mu \ge` ``share``, each parameter flagged where
    such a vector moves it by at least a tenth of its largest component (after scaling
    by the parameter's own variance, :math:`A^{-1}_{jj}`)."""
    n = len(A)
    try:
        L = np.linalg.cholesky(A)
    except np.linalg.LinAlgError:
        return np.ones(n, np.bool_)
    Li = np.linalg.inv(L)
    mu, V = np.linalg.eigh(Li @ B @ Li.T)

    out = np.zeros(n, np.bool_)
    scale = np.sqrt(np.clip(np.diag(np.linalg.inv(A)), 1e-300, None))
    for k in np.flatnonzero(mu >= share):
        # the direction in parameter space, x = L^-T v, each parameter in its own sigma
        x = np.abs(Li.T @ V[:, k]) / scale
        out |= x >= 0.1 * x.max()
    return out


class _BlockOut:
    """The per-row outputs of one block of :meth:`EquationEstimator.process`."""

    def __init__(self, N: int, n: int, record: bool) -> None:
        self.y = np.empty(N)
        self.eps = np.empty(N)
        self.eps_fixed = np.empty(N)
        self.flags = np.empty(N, np.uint8)
        self.rms = np.empty(N)
        self.theta = np.full((N, n), np.nan) if record else None
        self.theta_fixed = np.full((N, n), np.nan) if record else None
        #: the check filter's (phi, y) and the rows it counts
        self.check: tuple[F64, F64] | None = None
        self.check_use: npt.NDArray[np.bool_] | None = None


class EquationEstimator:
    """Builder, float RLS, fixed RLS and statistics of one equation."""

    def __init__(self, equation: Equation, dt: float, settings: EstimatorSettings,
                 energy: npt.ArrayLike | None = None, pending: Sequence[str] = (),
                 adapt: bool = True, noise: npt.ArrayLike | None = None) -> None:
        self.equation = equation
        #: covariance of the noise the filtered columns carry per row, unnormalised
        #: (:meth:`~canrls.estimation.model.RegressorBuilder.noise_covariance`; None: unknown)
        self.noise = None if noise is None else np.array(noise, dtype=np.float64)
        self.settings = settings
        self.dt = float(dt)
        self.builder = equation.builder(dt)
        n = equation.n
        s = settings
        names = [p.name for p in equation.parameters]
        #: whether the normalisation follows the data (:meth:`_adapt`): off for a probe
        self.adapt = bool(adapt)
        #: columns whose exponent follows the data (all but those bounded by their own
        #: function, which no value can outgrow); the output's always does
        self._adaptive = ~np.array(equation.intrinsic, np.bool_)
        self._adaptive_y = True
        #: columns (and the output) no used row has shown a value of yet
        self._pending = np.array([nm in pending for nm in names], np.bool_)
        self._pending_y = "output" in pending
        self.rescale_count = 0
        self.rescales: list[Rescale] = []
        #: ridge weight of each column, alpha_j = alpha * e_j (EstimatorSettings.ridge)
        self.ridge = s.ridge(n, energy)
        #: the prior a column that outgrew its exponent is raised to (:meth:`_adapt`):
        #: the weakest one at the start, which the fixed-point P format holds
        self._prior_floor = float(np.min(self.ridge))
        self.rls = RLS(n, lam=s.lam, alpha=self.ridge, trace_max=s.trace_max)
        # before a calibration (no energies) the prior is checked at its largest
        self.fixed_config = s.fixed_config(n, None if energy is None else self.ridge)
        self.frls = FixedRLS(self.fixed_config, n, lam=s.lam, alpha=self.ridge,
                             trace_max=s.trace_max)
        #: the same equation through the filter at half the cutoff (None where that
        #: filter cannot run at this period): its least-squares estimate, on the rows
        #: both filters have settled on, bounds the bias of the model's errors that the
        #: filter weighs (:meth:`bias`); a probe, whose estimates nobody reads, runs none
        self.check_builder: RegressorBuilder | None = None
        self.check_selector: SampleSelector | None = None
        if self.adapt:
            try:
                check = equation.model.with_cutoff(CHECK_CUTOFF * equation.model.cutoff_hz)
                check_eq = check.equation(equation.name)
                self.check_builder = check_eq.builder(dt)
                self.check_selector = SamplePolicy.for_equation(check_eq, self.dt,
                                                                s).selector()
            except ConfigError:
                pass
        #: which samples update the estimators (warm-up, gaps, speed limits)
        self.policy = SamplePolicy.for_equation(equation, self.dt, s)
        self.filler = self.policy.filler()
        self.selector = self.policy.selector()
        self.beta = min(1.0, self.dt / s.rms_time_s)
        #: the last used rows, for the colour of the residual (sigma); lags: the warm-up
        self.tail = ResidualTail(n, self.policy.warmup)
        self.reset()

    @property
    def warmup(self) -> int:
        """Samples of filter warm-up not used (:attr:`SamplePolicy.warmup`)."""
        return self.policy.warmup

    @property
    def min_speed(self) -> float:
        return self.policy.min_speed

    @property
    def max_speed(self) -> float:
        return self.policy.max_speed

    def reset(self) -> None:
        """Back to the prior; statistics cleared; the filter restarts."""
        n = self.equation.n
        self.builder.reset()
        self.rls.reset()
        self.frls.reset()
        self._M = np.zeros((n, n))
        self._v = np.zeros(n)
        self._s = np.zeros(3)
        # the check filter's sums: M2 = sum phi2 phi2', v2 = sum phi2 y2 (normalised)
        self._M2 = np.zeros((n, n))
        self._v2 = np.zeros(n)
        self._s2 = np.zeros(3)
        if self.check_builder is not None and self.check_selector is not None:
            self.check_builder.reset()
            self.check_selector.reset()
        self._rms_state = np.zeros(1)
        self.selector.reset()
        self.filler.reset()
        self.tail.reset()
        self.windup_steps = 0
        #: rows left out because a value was not finite (see RegressorBuilder)
        self.nonfinite_rows = 0
        self._since_nonfinite = self.warmup + 1  # rows since the last one

    def process(self, signals: Signals, record: bool = False) -> EquationBlock:
        filled, real = self.filler.fill(signals)
        # the rows in the filter's memory of a doubtful fill are not used either
        settling = self.filler.settling(filled, real)
        out = self._process(filled, real, record, settling)
        if real is None:
            return out
        # report the real samples only (the filled rows only kept the filter's time base)

        def pick(a: Any) -> Any:
            return None if a is None else a[real]

        # changes happen on used rows, which are real: their index among the real rows
        before: npt.NDArray[np.intp] = np.cumsum(real) - real
        changes = tuple((int(before[k]), d, dy) for k, d, dy in out.changes)
        return EquationBlock(
            equation=out.equation, t=out.t[real], y=out.y[real], eps=out.eps[real],
            eps_fixed=out.eps_fixed[real], used=out.used[real],
            online_rms=out.online_rms[real], flags=out.flags[real],
            theta=pick(out.theta), theta_fixed=pick(out.theta_fixed), phi=pick(out.phi),
            changes=changes)

    def _regressors(self, signals: Signals, restart: npt.NDArray[np.bool_], restarts: int,
                    builder: RegressorBuilder | None = None
                    ) -> tuple[F64, F64, npt.NDArray[np.bool_] | None]:
        """(phi, y, rows with a non-finite value or None) of the block through
        ``builder`` (default: the equation's), the filter restarted at the ``restart``
        rows."""
        builder = self.builder if builder is None else builder
        N = len(restart)
        if restarts == 0 or (restarts == 1 and restart[0]):
            # one piece (the common case): no slicing, no joining
            if restarts:
                builder.reset()
            phi, y, _, nonfinite = builder.regressors(signals)
            return phi, y, nonfinite
        # the filter restarts at every gap (and at the start): split the block there
        bounds = [int(k) for k in np.flatnonzero(restart)] + [N]
        if bounds[0] != 0:
            bounds.insert(0, 0)
        parts = []
        for a, b in zip(bounds[:-1], bounds[1:], strict=True):
            if restart[a]:
                builder.reset()
            parts.append(builder.process(signals.slice(a, b)))
        nonfinite = None
        if any(p.nonfinite is not None for p in parts):
            nonfinite = np.concatenate([np.zeros(len(p), np.bool_) if p.nonfinite is None
                                        else p.nonfinite for p in parts])
        return (np.concatenate([p.phi for p in parts]), np.concatenate([p.y for p in parts]),
                nonfinite)

    def _skip_nonfinite(self, nonfinite: npt.NDArray[np.bool_] | None,
                        use: npt.NDArray[np.bool_]) -> None:
        """Leave out of ``use`` the rows that had a non-finite value (replaced by the
        builder) and the ``warmup`` rows after each, as after a gap; counted in
        ``nonfinite_rows``."""
        rows = np.arange(len(use))
        if nonfinite is None:
            since = self._since_nonfinite + 1 + rows
        else:
            self.nonfinite_rows += int(np.count_nonzero(nonfinite))
            last = np.maximum.accumulate(np.where(nonfinite, rows, -1))
            since = np.where(last >= 0, rows - last, self._since_nonfinite + 1 + rows)
        use &= since > self.warmup
        self._since_nonfinite = int(since[-1])

    def _fixed_block(self, phi: F64, y: F64, record: bool
                     ) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64] | None,
                                npt.NDArray[np.int64], npt.NDArray[np.int64],
                                npt.NDArray[np.uint8], int]:
        """The fixed-point estimator over the used rows: inputs rounded, then its kernel."""
        Pq, Yq = self.frls.quantize_block(phi, y)
        return self.frls.run_block(Pq, Yq, record)

    def _process(self, signals: Signals, real: npt.NDArray[np.bool_] | None,
                 record: bool, settling: npt.NDArray[np.bool_] | None = None) -> EquationBlock:
        eq = self.equation
        t = np.ascontiguousarray(signals.t, dtype=np.float64)
        N = len(t)
        use = np.empty(N, np.bool_)
        if N == 0:
            # nothing to filter or estimate
            e = np.zeros(0)
            return EquationBlock(
                equation=eq.name, t=t, y=e, eps=e.copy(), eps_fixed=e.copy(), used=use,
                online_rms=e.copy(), flags=np.zeros(0, np.uint8),
                theta=np.zeros((0, eq.n)) if record else None,
                theta_fixed=np.zeros((0, eq.n)) if record else None,
                phi=np.zeros((0, eq.n)) if record else None)
        sel = self.selector.select(t, signals.speed)
        restart, use = sel.restart, sel.use
        if real is not None:
            use &= real
        if settling is not None:
            use &= ~settling
        phi, y, nonfinite = self._regressors(signals, restart, sel.restarts)
        if nonfinite is not None or self._since_nonfinite <= self.warmup:
            self._skip_nonfinite(nonfinite, use)
        out = _BlockOut(N, eq.n, record)
        if self.check_builder is not None and self.check_selector is not None:
            # the check filter, in the normalisation of the block's start; its rows: those
            # the estimators use, once its own (longer) warm-up has passed
            self.check_builder.normalise_as(eq.scaling)
            csel = self.check_selector.select(t, signals.speed)
            out.check = self._regressors(signals, csel.restart, csel.restarts,
                                         self.check_builder)[:2]
            out.check_use = csel.use & use
        # rows up to the next one that asks for a new normalisation, then that change
        # (exact: the float estimate does not move), then on: never more than a few
        a = 0
        changes: list[tuple[int, npt.NDArray[np.int64], int]] = []
        while True:
            k = self._next_change(phi, y, use, a) if self.adapt else N
            self._estimate(phi, y, use, a, k, out)
            if k >= N:
                break
            d, dy = self._adapt(phi, y, k, float(t[k]))
            changes.append((k, d, dy))
            if out.check is not None:
                np.ldexp(out.check[0][k:], -d, out=out.check[0][k:])
                np.ldexp(out.check[1][k:], -dy, out=out.check[1][k:])
            a = k
        return EquationBlock(
            equation=eq.name, t=t, y=out.y, eps=out.eps, eps_fixed=out.eps_fixed, used=use,
            online_rms=out.rms, flags=out.flags, theta=out.theta,
            theta_fixed=out.theta_fixed, phi=phi if record else None,
            changes=tuple((k, tuple(int(x) for x in d), dy) for k, d, dy in changes))

    def _estimate(self, phi: F64, y: F64, use: npt.NDArray[np.bool_], a: int, b: int,
                  out: _BlockOut) -> None:
        """Rows ``a:b`` of a block through both estimators and the bookkeeping."""
        if b <= a:
            return
        eq = self.equation
        phi_ab, y_ab, use_ab = phi[a:b], y[a:b], use[a:b]
        used = int(np.count_nonzero(use_ab))
        n_ab = b - a
        # the used rows (None: all of them, or none)
        rows = np.flatnonzero(use_ab) if 0 < used < n_ab else None
        record = out.theta is not None
        if used:
            phi_u = phi_ab if rows is None else phi_ab[rows]
            y_u = y_ab if rows is None else y_ab[rows]
            # on a large block the fixed-point estimator runs in a thread meanwhile: the
            # two share no state, and their kernels release the GIL
            fixed = Background(self._fixed_block, phi_u, y_u, record,
                               name="canrls fixed point") if used >= OVERLAP_ROWS else None
            try:
                eps_run, theta_u, _, flags_u, _ = self.rls.run_block(phi_u, y_u, record)
                eps_u = cast(F64, eps_run)  # the pipeline's RLS runs in float64 (its default)
                self.tail.push(phi_u, y_u)
            finally:
                if fixed is not None:
                    fixed.join()
            epsq_u, thetaq_u, _, _, flagsq_u, _ = (
                fixed.result() if fixed is not None else self._fixed_block(phi_u, y_u, record))
        else:
            # no row updates the estimators (all in a warm-up): they are left as they are
            eps_u, epsq_u = np.zeros(0), np.zeros(0, np.int64)
            flags_u = flagsq_u = np.zeros(0, np.uint8)
            theta_u = thetaq_u = None
        # after the estimators, row by row in C (canrls._kernels.bookkeeping): spread the
        # used rows' errors (the fixed-point one is epsq * lsb, exact) and flags over the
        # rows, 0 elsewhere; the residual mean square r <- r + beta (eps^2 - r) on used
        # rows; y, the errors and sqrt(r) in the output unit (x 2**s_y, one rounding);
        # the sums M += phi phi' (upper triangle), v += phi y, s += [1, y, y^2]
        self.windup_steps += _kernels.bookkeeping(
            phi_ab, y_ab, use_ab, eps_u, epsq_u, self.fixed_config.eps.lsb, flags_u,
            flagsq_u, self._M, self._v, self._s, self.beta, self._rms_state,
            eq.scaling.output, out.y[a:b], out.eps[a:b], out.eps_fixed[a:b],
            out.flags[a:b], out.rms[a:b])
        if out.check is not None and out.check_use is not None:
            # the check filter's sums, row by row in C (the same bits in any blocks):
            # M2 += phi2 phi2' (upper triangle), v2 += phi2 y2, s2 += [1, y2, y2^2]
            _kernels.accumulate(out.check[0][a:b], out.check[1][a:b], out.check_use[a:b],
                                self._M2, self._v2, self._s2)
        if (out.theta is not None and out.theta_fixed is not None  # record
                and theta_u is not None and thetaq_u is not None):
            # rows in a warm-up did not update: they stay nan
            at = slice(a, b) if rows is None else rows + a
            out.theta[at] = eq.to_physical(theta_u)
            out.theta_fixed[at] = eq.to_physical(self.frls.config.theta.to_float(thetaq_u))

    # -- the normalisation follows the data -----------------------------------------------
    def _next_change(self, phi: F64, y: F64, use: npt.NDArray[np.bool_], a: int) -> int:
        """The first used row from ``a`` on where a data-scaled column or the output
        exceeds :data:`RESCALE_LIMIT`, or a pending one is not zero; ``len(y)``: none."""
        N = len(y)
        grow, first = self._adaptive & ~self._pending, self._pending
        grow_y = self._adaptive_y and not self._pending_y
        if not (grow.any() or first.any() or grow_y or self._pending_y):
            return N
        sub, ys, u = phi[a:], y[a:], use[a:]
        hit = np.zeros(N - a, np.bool_)
        if grow.any():
            hit |= (np.abs(sub[:, grow]) > RESCALE_LIMIT).any(axis=1)
        if first.any():
            hit |= (sub[:, first] != 0.0).any(axis=1)
        if grow_y:
            hit |= np.abs(ys) > RESCALE_LIMIT
        if self._pending_y:
            hit |= ys != 0.0
        hit &= u
        i = int(np.argmax(hit)) if len(hit) else 0
        return a + i if len(hit) and hit[i] else N

    def _adapt(self, phi: F64, y: F64, k: int, t: float
               ) -> tuple[npt.NDArray[np.int64], int]:
        """Change the normalisation at row ``k`` (:meth:`_next_change`): every column and
        the output that outgrew its exponent get one that puts row ``k`` at most
        1/:data:`RESCALE_HEADROOM` of full scale, and a pending one the exponent of the
        calibration's rule for its first value, with its prior (``alpha`` times that
        value's square, as the window's energy would give); everything the estimators
        and the sums hold is rescaled exactly, and so are the rows from ``k`` on.
        Returns the change of every column's exponent and of the output's."""
        n = self.equation.n
        d = np.zeros(n, np.int64)
        first: list[tuple[int, float]] = []
        for j in range(n):
            v = abs(float(phi[k, j]))
            if self._pending[j] and v != 0.0:
                d[j] = exponent_for(v, RMS_HEADROOM)
                first.append((j, math.ldexp(v, -int(d[j])) ** 2))
            elif self._adaptive[j] and not self._pending[j] and v > RESCALE_LIMIT:
                d[j] = exponent_for(v, RESCALE_HEADROOM)
        dy = 0
        vy = abs(float(y[k]))
        first_y = self._pending_y and vy != 0.0
        if first_y:
            dy = exponent_for(vy, RMS_HEADROOM)
        elif self._adaptive_y and not self._pending_y and vy > RESCALE_LIMIT:
            dy = exponent_for(vy, RESCALE_HEADROOM)
        # theta_j takes 2**(d_j - d_y): the output moves with the columns where that
        # would take an estimate beyond half its bound (a column and the output growing
        # together, one row apart, would otherwise saturate it for a moment)
        th = np.abs(np.ldexp(np.asarray(self.rls.theta, dtype=np.float64), d - dy))
        big = float(np.max(th)) if len(th) else 0.0
        if big > 0.5 * self.settings.theta_max and math.isfinite(big):
            dy += exponent_for(big, 2.0 / self.settings.theta_max)
        # a column that outgrew its exponent takes, in its new units, the weakest prior
        # the estimator started with (alpha * MIN_ENERGY or more once calibrated): the one
        # it had, rescaled with it, would weigh 2**(2 d_j) times less than the rule gives
        grew = {int(j): self._prior_floor for j in np.flatnonzero(d) if not self._pending[j]}
        self._rescale(d, dy, t, grew)
        if first_y:
            self._pending_y = False
        for j, e in first:
            # the column was zero on every used row: its prior alone holds it, and is set
            # now as if it had been from the start (alpha_j = alpha * e_j)
            self._pending[j] = False
            new = float(self.settings.alpha) * e
            self.rls.set_prior(j, new)
            self.frls.set_prior(j, new)
            self.ridge[j] = new
        np.ldexp(phi[k:], -d, out=phi[k:])
        if dy:
            np.ldexp(y[k:], -dy, out=y[k:])
        return d, dy

    def _rescale(self, d: npt.NDArray[np.int64], dy: int, t: float,
                 prior: Mapping[int, float]) -> None:
        r"""Exponents ``s_j += d_j``, ``s_y += d_y``: ``phi_j`` takes ``2**-d_j``,
        ``theta_j`` ``2**(d_j - d_y)``, ``P_jk`` ``2**(d_j + d_k)``, the sums and the
        residual's statistics alike (exact powers of two; the float estimate in
        physical units does not move); then the priors ``{j: alpha_j}`` are raised
        (:meth:`~canrls.estimation.rls.RLS.rescale`)."""
        eq = self.equation
        sc = eq.scaling
        names = [p.name for p in eq.parameters]
        for j in np.flatnonzero(d):
            self._note(t, names[j], sc.columns[j], sc.columns[j] + int(d[j]),
                       "first" if self._pending[j] else "grew")
        if dy:
            self._note(t, "output", sc.output, sc.output + dy,
                       "first" if self._pending_y else "grew")
        self.rls.rescale(d, dy, prior)
        self.frls.rescale(d, dy, prior)
        self.ridge = np.ldexp(self.ridge, -2 * d)
        for k, a in prior.items():
            self.ridge[k] = a
        # M = sum phi phi', v = sum phi y, s = [N, sum y, sum y^2], r: mean square of eps
        self._M = np.ldexp(self._M, -(d[:, None] + d[None, :]))
        self._v = np.ldexp(self._v, -(d + dy))
        self._M2 = np.ldexp(self._M2, -(d[:, None] + d[None, :]))
        self._v2 = np.ldexp(self._v2, -(d + dy))
        self._s2[1:] = np.ldexp(self._s2[1:], [-dy, -2 * dy])
        self._s[1:] = np.ldexp(self._s[1:], [-dy, -2 * dy])
        self._rms_state = np.ldexp(self._rms_state, -2 * dy)
        self.tail.rescale(d, dy)
        exps = {"output": sc.output + dy,
                **{nm: s_j + int(d_j) for nm, s_j, d_j in zip(names, sc.columns, d, strict=True)}}
        model = eq.model.with_scaling({**eq.model.exponents, eq.name: exps})
        self.equation = model.equation(eq.name)
        self.builder.rescale(self.equation)

    def _note(self, t: float, name: str, old: int, new: int, why: str) -> None:
        self.rescale_count += 1
        if len(self.rescales) < MAX_RESCALES_LISTED:
            self.rescales.append(Rescale(t, name, old, new, why))

    @property
    def pending(self) -> tuple[str, ...]:
        """The output and the columns no used row has shown a value of yet."""
        names = [p.name for p, w in zip(self.equation.parameters, self._pending, strict=True)
                 if w]
        return (("output",) if self._pending_y else ()) + tuple(names)

    # -- results ----------------------------------------------------------------------
    @property
    def samples(self) -> int:
        return int(self._s[0])

    def residual_stats(self, theta_norm: F64 | None = None) -> tuple[float, float, float, float]:
        """(residual RMS, fit %, R², output RMS) of ``theta_norm`` (default: the float estimate)."""
        eq = self.equation
        th = self.rls.theta if theta_norm is None else theta_norm
        N, sy, syy = self._s
        if N == 0:
            return math.nan, math.nan, math.nan, math.nan
        M = np.triu(self._M) + np.triu(self._M, 1).T
        # RSS = sum y^2 - 2 theta' sum(phi y) + theta' (sum phi phi') theta
        rss = max(0.0, float(syy - 2.0 * th @ self._v + th @ M @ th))
        # TSS = sum (y - mean y)^2
        tss = max(0.0, float(syy - sy * sy / N))
        scale = math.ldexp(1.0, eq.scaling.output)
        rms = math.sqrt(rss / N) * scale
        fit = 100.0 * (1.0 - math.sqrt(rss / tss)) if tss > 0 else math.nan
        r2 = 1.0 - rss / tss if tss > 0 else math.nan
        return rms, fit, r2, math.sqrt(syy / N) * scale

    def divergence(self) -> float:
        """Largest fixed-vs-float difference relative to max(|float|, 3 sigma) over parameters
        (:func:`divergence`)."""
        return divergence(self.rls.theta.tolist(), self.frls.theta_float.tolist(),
                          self.rls.std().tolist())

    def parameters(self) -> list[ParameterEstimate]:
        """The parameter estimates alone, without the fit statistics of :meth:`estimates`."""
        eq = self.equation
        value = eq.to_physical(self.rls.theta)
        # sigma = sqrt(kappa sigma^2 diag P): the RLS formula, widened by the colour, and
        # the noise's pull on the estimate added: sqrt(sigma_stat^2 + bias^2)
        stat = eq.sigma_to_physical(self.rls.std() * math.sqrt(self.sigma_inflation()))
        bound, noisy = self.bias()
        bias = np.abs(eq.to_physical(bound))
        # where the noise can explain the columns, the estimate itself stands for the bias
        bias = np.where(noisy, np.maximum(bias, np.abs(value)), bias)
        sigma = np.hypot(stat, bias)
        fixed = eq.to_physical(self.frls.theta_float)
        share = prior_share(self.rls.P, self.rls.ridge)
        return [ParameterEstimate(p.name, p.unit, p.effect, eq.name, p.description, v, s, f,
                                  float(sh), float(b), bool(nz))
                for p, v, s, f, sh, b, nz in zip(eq.parameters, value.tolist(), sigma.tolist(),
                                                 fixed.tolist(), share.tolist(), bias.tolist(),
                                                 noisy.tolist(), strict=True)]

    def bias(self) -> tuple[F64, npt.NDArray[np.bool_]]:
        r"""What the model's errors can do to the estimate: a bound on each parameter's
        bias (normalised) and which parameters the measurement noise can explain.

        *The bound.* The filtered equation holds for any filter if the model is right;
        the errors it makes do not: errors in the variables (a noisy speed in the inertia
        and viscous columns pulls the estimate towards zero, more the wider the filter),
        the hold between samples, what happens at reversals. The least-squares estimates
        through this filter and through the check filter at :data:`CHECK_CUTOFF` of its
        cutoff, on the rows both use, with the same prior,
        :math:`\hat\theta_1 = (M + R)^{-1} v` and :math:`\hat\theta_2 = (M_2 + R)^{-1}
        v_2`, differ by what such errors do; a bias that falls like the cutoff or faster
        is at most :data:`CHECK_FACTOR` times the difference.

        *The noise.* With the columns' noise covariance :attr:`noise` (white noise of the
        size measured on the calibration window), :math:`B = N\Sigma`: where
        :math:`A - B` (:math:`A = M + R`) is not positive definite, the noise could
        explain all the data show of some combination of the columns; the parameters
        that combination involves are not identifiable from these data
        (:func:`_noise_explains`). The white noise overstates what a speed differenced
        from an encoder carries through the filter, which is why it decides only this
        and does not size the bound.
        """
        n = self.equation.n
        N = float(self._s[0])
        bound = np.zeros(n)
        noisy = np.zeros(n, np.bool_)
        if N <= 0:
            return bound, noisy
        M = np.triu(self._M) + np.triu(self._M, 1).T
        A = M + np.diag(self.ridge)
        if self._s2[0] > n:
            M2 = np.triu(self._M2) + np.triu(self._M2, 1).T
            try:
                # theta1 = (M + R)^-1 v, theta2 = (M2 + R)^-1 v2
                t1 = np.linalg.solve(A, self._v)
                t2 = np.linalg.solve(M2 + np.diag(self.ridge), self._v2)
                bound = CHECK_FACTOR * np.abs(t1 - t2)
            except np.linalg.LinAlgError:
                bound = np.full(n, math.inf)
            bound = np.where(np.isfinite(bound), bound, math.inf)
        if self.noise is not None and np.any(self.noise):
            d = np.ldexp(np.ones(n), -np.asarray(self.equation.scaling.columns, np.int64))
            B = N * (self.noise * d[:, None] * d[None, :])
            noisy = _noise_explains(A, B)
        return bound, noisy

    def estimates(self) -> tuple[list[ParameterEstimate], EquationFit]:
        eq = self.equation
        params = self.parameters()
        rms, fit, r2, trms = self.residual_stats()
        exc = self.rls.excitation()
        fit_obj = EquationFit(
            equation=eq.name, output=eq.output.description, unit=eq.output.unit,
            samples=self.samples, residual_rms=rms, fit_percent=fit, r2=r2,
            output_rms=trms,
            online_rms=math.sqrt(self._rms_state[0]) * math.ldexp(1.0, eq.scaling.output),
            divergence=self.divergence(), saturations=self.frls.saturations.nonzero(),
            windup_steps=self.windup_steps, low_excitation=bool(exc.low),
            condition=float(exc.cond), nonfinite_rows=self.nonfinite_rows,
            sigma_inflation=self.sigma_inflation(), exponents=self.exponents,
            rescale_count=self.rescale_count, rescales=tuple(self.rescales),
            pending=self.pending, fixed_config=self.frls.config.label)
        return params, fit_obj

    @property
    def exponents(self) -> dict[str, int]:
        """The normalisation's exponents now, ``{"output": s_y, parameter: s_j}``."""
        sc = self.equation.scaling
        return {"output": sc.output, **{p.name: s for p, s in
                                        zip(self.equation.parameters, sc.columns, strict=True)}}

    def sigma_inflation(self) -> float:
        """``kappa`` of the current float estimate (:class:`ResidualTail`)."""
        return self.tail.inflation(np.asarray(self.rls.theta, dtype=np.float64))

    def state(self) -> dict[str, Any]:
        return {"rls": self.rls.state(), "fixed": self.frls.state(), "M": self._M.copy(),
                "v": self._v.copy(), "s": self._s.copy(), "rms": self._rms_state.copy(),
                "M2": self._M2.copy(), "v2": self._v2.copy(), "s2": self._s2.copy(),
                "windup_steps": self.windup_steps, "nonfinite_rows": self.nonfinite_rows,
                "tail": self.tail.state(), "pending": list(self.pending),
                "noise": None if self.noise is None else self.noise.copy(),
                "rescale_count": self.rescale_count,
                "rescales": [r.to_dict() for r in self.rescales]}

    def restore(self, d: Mapping[str, Any]) -> None:
        """Continue from :meth:`state` (the filter restarts: the next samples warm it up)."""
        self.rls = RLS.from_state(d["rls"])
        self.frls = FixedRLS.from_state(d["fixed"])
        self.fixed_config = self.frls.config  # the formats the restored state is in
        self.ridge = np.array(self.rls.ridge, dtype=np.float64)
        if "pending" in d:
            pend = set(d["pending"])
            self._pending = np.array([p.name in pend for p in self.equation.parameters],
                                     np.bool_)
            self._pending_y = "output" in pend or OLD_OUTPUT_KEY in pend  # an older checkpoint
        self.rescale_count = int(d.get("rescale_count", 0))
        noise = d.get("noise")
        n = self.equation.n
        self.noise = None if noise is None else np.array(noise, dtype=np.float64).reshape(n, n)
        self.rescales = [Rescale(float(r["t"]), str(r["name"]), int(r["old"]),
                                 int(r["new"]), str(r["why"]))
                         for r in d.get("rescales", [])][:MAX_RESCALES_LISTED]
        self._M = np.array(d["M"], dtype=np.float64)
        self._v = np.array(d["v"], dtype=np.float64)
        self._s = np.array(d["s"], dtype=np.float64)
        self._rms_state = np.array(d["rms"], dtype=np.float64)
        n = self.equation.n
        self._M2 = np.array(d.get("M2", np.zeros((n, n))), dtype=np.float64)
        self._v2 = np.array(d.get("v2", np.zeros(n)), dtype=np.float64)
        self._s2 = np.array(d.get("s2", np.zeros(3)), dtype=np.float64)
        self.windup_steps = int(d["windup_steps"])
        self.nonfinite_rows = int(d.get("nonfinite_rows", 0))
        self._since_nonfinite = self.warmup + 1
        if "tail" in d:
            self.tail.restore(d["tail"])
        self.builder.reset()
        self.selector.reset()
        self.filler.reset()
        if self.check_builder is not None and self.check_selector is not None:
            self.check_builder.reset()
            self.check_selector.reset()


class Pipeline:
    """Samples in, estimates out: one :class:`EquationEstimator` per model equation.

    Parameters
    ----------
    model : the model to identify
    dt : sample period [s] (the control period of the drive)
    settings : estimator settings (:class:`EstimatorSettings`)
    energy : ``{equation name: mean square of each normalised column}`` measured on
        the calibration window (:func:`canrls.processor.calibrate`); the ridge prior
        is scaled with it (:meth:`EstimatorSettings.ridge`). ``None``:
        :math:`P_0 = I/\alpha` in normalised units, which weighs on the parameters of
        weakly scaled columns and so depends on the ranges.
    pending : ``{equation name: names}`` of the output and columns the calibration
        window showed nothing of (:class:`~canrls.processor.WindowScaling`)
    noise : ``{equation name: noise covariance of the filtered columns}`` (unnormalised;
        :meth:`EquationEstimator.bias`)
    adapt : whether the normalisation follows the data (off: a probe of the window,
        without the check filter of :meth:`EquationEstimator.bias`)
    """

    def __init__(self, model: Model, dt: float, settings: EstimatorSettings | None = None,
                 energy: Mapping[str, npt.ArrayLike] | None = None,
                 pending: Mapping[str, Sequence[str]] | None = None,
                 noise: Mapping[str, npt.ArrayLike] | None = None,
                 adapt: bool = True) -> None:
        if not (dt > 0 and math.isfinite(dt)):
            raise ConfigError(f"sample period dt = {dt!r}: must be > 0")
        self._model = model
        self.dt = float(dt)
        self.settings = settings or EstimatorSettings()
        self.energy = None if energy is None else {
            k: np.asarray(v, dtype=np.float64).copy() for k, v in energy.items()}
        self.estimators = tuple(
            EquationEstimator(eq, self.dt, self.settings,
                              None if energy is None else energy[eq.name],
                              (pending or {}).get(eq.name, ()), adapt,
                              (noise or {}).get(eq.name))
            for eq in model.equations)
        self.samples = 0

    @property
    def model(self) -> Model:
        """The model, with the exponents its equations have now (they follow the data)."""
        if any(e.equation is not eq for e, eq in zip(self.estimators, self._model.equations,
                                                     strict=True)):
            self._model = self._model.with_scaling(
                {**self._model.exponents, **{e.equation.name: e.exponents
                                             for e in self.estimators}})
            for e in self.estimators:
                e.equation = self._model.equation(e.equation.name)
        return self._model

    def process(self, signals: Signals, record: bool = False) -> PipelineBlock:
        """Feed a block of samples (any size, including 0)."""
        blocks = tuple(e.process(signals, record) for e in self.estimators)
        self.samples += len(signals)
        return PipelineBlock(len(signals), blocks)

    def run(self, blocks: Iterable[Signals]) -> Estimates:
        """Process every block, then return :meth:`estimates`."""
        for b in blocks:
            self.process(b)
        return self.estimates()

    def estimates(self) -> Estimates:
        params: list[ParameterEstimate] = []
        fits: list[EquationFit] = []
        for e in self.estimators:
            p, f = e.estimates()
            params.extend(p)
            fits.append(f)
        return Estimates(tuple(params), tuple(fits), self._model.effect_names, self._model.kt)

    # -- control (command frames) ---------------------------------------------------
    def reset(self) -> None:
        for e in self.estimators:
            e.reset()

    def freeze(self) -> None:
        for e in self.estimators:
            e.rls.freeze()
            e.frls.freeze()

    def resume(self) -> None:
        for e in self.estimators:
            e.rls.resume()
            e.frls.resume()

    @property
    def frozen(self) -> bool:
        return any(e.rls.frozen for e in self.estimators)

    def parameters(self) -> tuple[tuple[ParameterEstimate, ...], ...]:
        """Each equation's parameter estimates, without the fit statistics of
        :meth:`estimates` (a third of its cost: what a live publication needs)."""
        return tuple(tuple(e.parameters()) for e in self.estimators)

    def update_counts(self) -> tuple[tuple[int, int], ...]:
        """Updates applied since the last reset, ``(float, fixed)`` per equation (frozen
        steps and overflowing steps do not count)."""
        return tuple((int(e.rls.count), int(e.frls.count)) for e in self.estimators)

    def set_lambda(self, lam: float) -> None:
        """Change the forgetting factor of both estimators (validated); it lives in
        :attr:`settings`, which a pipeline for a changed model is built from."""
        self.settings = dataclasses.replace(self.settings, lam=lam)
        for e in self.estimators:
            e.settings = self.settings
            e.rls.set_lambda(lam)
            e.frls.set_lambda(lam)

    def with_model(self, model: Model, warm: bool = True,
                   energy: Mapping[str, npt.ArrayLike] | None = None,
                   pending: Mapping[str, Sequence[str]] | None = None,
                   noise: Mapping[str, npt.ArrayLike] | None = None) -> Pipeline:
        """A new pipeline for ``model`` (e.g. an effect added or removed).

        With ``warm`` (default) the parameters both models share start from their
        current estimates (float and fixed point alike) instead of zero, so adding an
        effect does not make the others converge again; the covariance restarts from
        the prior for every parameter, so all of them adapt. ``energy``, ``pending``:
        the new model's column energies and pending columns (as for :class:`Pipeline`).
        """
        new = Pipeline(model, self.dt, self.settings, energy, pending, noise)
        if self.frozen:
            new.freeze()
        if not warm:
            return new
        old = {e.equation.name: e for e in self.estimators}
        for est in new.estimators:
            prev = old.get(est.equation.name)
            if prev is None:
                continue
            names = [p.name for p in prev.equation.parameters]
            phys = prev.equation.to_physical(prev.rls.theta)
            phys_fx = prev.equation.to_physical(prev.frls.theta_float)
            eq = est.equation
            th = np.zeros(eq.n)
            th_fx = np.zeros(eq.n)
            for j, p in enumerate(eq.parameters):
                if p.name in names:
                    k = names.index(p.name)
                    th[j], th_fx[j] = phys[k], phys_fx[k]
            st = est.rls.state()
            st["theta"] = np.asarray(eq.to_normalised(th), dtype=st["theta"].dtype)
            est.rls = RLS.from_state(st)
            fst = est.frls.state()
            q = est.fixed_config.theta
            fst["theta"] = np.array([max(q.lo, min(q.hi, q.to_int(float(v))))
                                     for v in eq.to_normalised(th_fx)], dtype=np.int64)
            est.frls = FixedRLS.from_state(fst)
        return new

    @property
    def saturations(self) -> SaturationCounts:
        total = None
        for e in self.estimators:
            total = e.frls.saturations if total is None else total + e.frls.saturations
        assert total is not None
        return total

    def state(self) -> dict[str, Any]:
        return {"samples": self.samples, "model": self.model.to_dict(),
                "estimators": [e.state() for e in self.estimators]}

    def restore(self, d: Mapping[str, Any]) -> None:
        ests = d["estimators"]
        if len(ests) != len(self.estimators):
            raise ConfigError("checkpoint has a different number of equations than the model")
        for e, s in zip(self.estimators, ests, strict=True):
            e.restore(s)
        self.samples = int(d["samples"])
        # a forgetting factor set by a command lives in the state
        lam = self.estimators[0].rls.lam if self.estimators else self.settings.lam
        if lam != self.settings.lam:
            self.settings = dataclasses.replace(self.settings, lam=lam)
            for e in self.estimators:
                e.settings = self.settings
