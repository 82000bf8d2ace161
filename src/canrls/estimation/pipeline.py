r"""The pure pipeline: samples -> regressors -> float and fixed RLS -> estimates.

:class:`Pipeline` is shared by the live daemon (``canrls run``) and the offline replay
(``canrls fit``, ``canrls diagnose``). It takes :class:`~canrls.signals.Signals`
blocks of any size and carries every state across them, sample by sample in the C
kernels of ``canrls._kernels`` (``src/canrls/c/kernels.c``) and in the fixed-point
kernels, so the same samples give the same parameters bit for bit whatever the block
sizes (the replay reads 64 k frames at a time, the daemon whatever has arrived).

Per equation of the model (mechanical, and electrical when present):

1. the :class:`~canrls.estimation.model.RegressorBuilder` filters target and columns with the
   state-variable filter and normalises them by powers of two;
2. samples inside the filter's warm-up (after the start, a reset or a gap in the
   sample times) are not used: the filter's zero initial state does not match the
   signals there, so the filtered equation does not hold yet (short gaps are filled;
   :class:`~canrls.estimation.selection.SamplePolicy` decides, for the diagnosis too);
3. the float reference :class:`~canrls.estimation.rls.RLS` and the fixed-point
   :class:`~canrls.estimation.fixed.FixedRLS` (inputs quantised at the boundary) update on the
   same rows;
4. the sufficient statistics (``sum phi phi'``, ``sum phi y``, ``sum y^2``) accumulate,
   so that the residual of the final estimate over all data, the fit and
   :math:`R^2` come without a second pass, in memory independent of the log length.

Goodness of fit, as MATLAB's ``compare``:

.. math::

    \mathrm{fit} = 100\,\Big(1 - \frac{\lVert y - \Phi\hat\theta\rVert}
                                    {\lVert y - \bar y\rVert}\Big), \qquad
    R^2 = 1 - \frac{\lVert y - \Phi\hat\theta\rVert^2}{\lVert y - \bar y\rVert^2}

computed on the filtered target, in the target's unit.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from canrls import _kernels
from canrls.background import Background
from canrls.errors import ConfigError
from canrls.estimation.colour import MAX_PRIOR_SHARE, ResidualTail, prior_share
from canrls.estimation.fixed import FixedConfig, FixedRLS, QFormat, SaturationCounts
from canrls.estimation.model import Equation, Model
from canrls.estimation.rls import RLS
from canrls.estimation.selection import SamplePolicy
from canrls.signals import Signals

__all__ = [
    "ALPHA_MAX",
    "ALPHA_MIN",
    "ENERGY_FLOOR",
    "EstimatorSettings",
    "ParameterEstimate",
    "EquationFit",
    "Estimates",
    "EquationBlock",
    "PipelineBlock",
    "EquationEstimator",
    "Pipeline",
    "divergence",
]

F64 = npt.NDArray[np.float64]

#: Smallest column energy (mean square, normalised units) the ridge is scaled with: a
#: column with less on the calibration window was not excited there, and its prior
#: then weighs as for a column at 2**-10 of full scale (P0 = 2**20/alpha, which the
#: fixed-point formats still hold for up to 12 columns).
ENERGY_FLOOR = 2.0 ** -20
#: Blocks of at least this many used rows run the fixed-point estimator in a thread
#: beside the float one (the offline replay's blocks; the daemon's, some 200 rows, stay
#: in one thread, where a hand-over would cost more than the overlap saves).
OVERLAP_ROWS = 4096
#: The ridge weight ``alpha`` (the prior weighs like ``alpha`` samples of each column)
#: from one billionth of a sample to a billion samples: P0 = diag(1/(alpha e_j)) then
#: has a fixed-point format at any energy from ENERGY_FLOOR to 1.
ALPHA_MIN, ALPHA_MAX = 1e-9, 1e9


# ------------------------------------------------------------------------ settings
@dataclass(frozen=True)
class EstimatorSettings:
    """Estimator settings shared by the float and the fixed-point RLS.

    Attributes
    ----------
    lam : forgetting factor :math:`\\lambda \\in (1/2, 1]` (memory ``1/(1-lam)`` samples)
    alpha : ridge weight: the prior weighs like ``alpha`` samples of each column
        (:math:`P_0 = \\mathrm{diag}(1/(\\alpha\\,\\bar e_j))` with the column's mean
        square :math:`\\bar e_j` on the calibration window, :class:`Pipeline`); without
        column energies, :math:`P_0 = I/\\alpha` in normalised units
    trace_max : bound on trace P (``None``: the prior's trace)
    calibration_s : seconds of samples at the start of a stream on which the front end
        (:mod:`canrls.processor`) measures the signal ranges the configuration does not
        give and the column energies of the prior; frozen and recorded
    word_bits, acc_bits, input_bits : fixed-point words (``input_bits=None``: ``word_bits``)
    theta_max : bound of the normalised parameters for the fixed-point theta format
    fixed_overrides : Q formats overriding the automatic choice (``{"P": QFormat(32, 24)}``)
    warmup_s : seconds of filter warm-up not used for estimation (``None``: 5 time
        constants of the SVF, ``5 / (zeta * wc)``)
    gap_periods : a sample-time step larger than this many periods restarts the filter
    rms_time_s : time constant of the running residual RMS reported live [s]
    max_phase_step : largest phase advance per sample [rad] of the fastest
        position-periodic column (``k * |omega| * dt`` for ``cogging:k``, unbalance
        ``k = 1``) at which a sample is used. Between samples the filter joins the
        samples of ``sin(k theta)`` by straight lines; that underestimates a sinusoid
        advancing by ``d`` rad per sample by about ``d^2/12``; samples faster than the
        limit (and the filter's settling after them) are skipped. Default ``inf`` (off):
        at such speeds the filter attenuates the periodic column so much that the
        error is negligible, while skipping the samples costs the speed-dependent
        parameters their fast data (``viscous.B`` came back 4-16 % off with
        ``cogging:24``/``36`` and a 0.3 rad guard).
    min_speed : samples with ``|omega|`` below this [rad/s, m/s] (and the filter's
        settling after them) are not used when the model has Coulomb or Stribeck
        friction: near standstill the measured speed's sign is noise and the drive
        sticks, which ``sgn_e`` does not model. ``None``: five times the Coulomb band.
    """

    lam: float = 1.0
    alpha: float = 0.01
    trace_max: float | None = None
    word_bits: int = 32
    acc_bits: int = 64
    input_bits: int | None = None
    theta_max: float = 16.0
    fixed_overrides: Mapping[str, QFormat] = field(default_factory=dict)
    warmup_s: float | None = None
    gap_periods: float = 3.5
    rms_time_s: float = 1.0
    max_phase_step: float = math.inf
    min_speed: float | None = None
    calibration_s: float = 2.0

    def __post_init__(self) -> None:
        if not (isinstance(self.lam, int | float) and 0.5 < self.lam <= 1.0):
            raise ConfigError(f"estimator.lambda = {self.lam!r}: must be in (0.5, 1]")
        if not (isinstance(self.alpha, int | float) and self.alpha > 0 and
                math.isfinite(self.alpha)):
            raise ConfigError(f"estimator.alpha = {self.alpha!r}: must be > 0")
        if not ALPHA_MIN <= self.alpha <= ALPHA_MAX:
            # P0 = diag(1 / (alpha e_j)), 2**-10 <= e_j <= 1: beyond these the fixed-point
            # format of P has no exponent for P0 (and the prior means nothing or all)
            raise ConfigError(f"estimator.alpha = {self.alpha!r}: must be from {ALPHA_MIN:g} "
                              f"to {ALPHA_MAX:g} (the prior weighs like alpha samples of "
                              f"each column)")
        if self.gap_periods <= 1.0:
            raise ConfigError(f"estimator.gap_periods = {self.gap_periods!r}: must be > 1")
        if not self.max_phase_step > 0:
            raise ConfigError(f"estimator.max_phase_step = {self.max_phase_step!r}: must be > 0")
        if self.rms_time_s <= 0:
            raise ConfigError(f"estimator.rms_time_s = {self.rms_time_s!r}: must be > 0")
        if not (self.calibration_s > 0 and math.isfinite(self.calibration_s)):
            raise ConfigError(
                f"estimator.calibration_s = {self.calibration_s!r}: must be > 0 seconds")

    def ridge(self, n: int, energy: npt.ArrayLike | None = None) -> F64:
        r"""The ridge weight of each of ``n`` columns: :math:`\alpha_j = \alpha\,\bar e_j`.

        ``energy`` holds the columns' mean squares :math:`\bar e_j` in normalised units
        (``None``: 1 each, the prior :math:`P_0 = I/\alpha`), floored at
        :data:`ENERGY_FLOOR`. The penalty :math:`\alpha\sum_j \bar e_j\theta_j^2` is
        then ``alpha`` times the mean square of each term :math:`\varphi_j\theta_j`:
        the same in any normalisation, so the scaling changes rounding, never the prior.
        """
        if energy is None:
            return np.full(n, float(self.alpha))
        e = np.asarray(energy, dtype=np.float64)
        if e.shape != (n,) or not np.all(np.isfinite(e)):
            raise ConfigError(f"column energies {energy!r}: need {n} finite values")
        # alpha_j = alpha * max(e_j, floor)
        return float(self.alpha) * np.maximum(e, ENERGY_FLOOR)

    def fixed_config(self, n: int, ridge: npt.ArrayLike | None = None) -> FixedConfig:
        """The automatic fixed-point configuration for ``n`` parameters (``ridge``: the
        weights :math:`\alpha_j`, default ``alpha`` for all)."""
        alpha = self.alpha if ridge is None else ridge
        return FixedConfig.auto(n, alpha, self.lam, theta_max=self.theta_max,
                                word_bits=self.word_bits, acc_bits=self.acc_bits,
                                input_bits=self.input_bits, trace_max=self.trace_max,
                                **dict(self.fixed_overrides))


# ------------------------------------------------------------------------- results
def divergence(theta: Sequence[float], fixed: Sequence[float], sigma: Sequence[float]) -> float:
    """Fixed point against float: ``max_j |fixed_j - theta_j| / max(|theta_j|, 3 sigma_j)``.

    A NaN sigma (not known yet) counts as 0, a zero or NaN reference as 1; a NaN
    difference makes the result NaN; no parameter gives 0. Pure Python: for the few
    parameters of a model this is several times faster than numpy.
    """
    worst = 0.0
    for th, fx, sd in zip(theta, fixed, sigma, strict=True):
        ref = abs(th)
        if 3.0 * sd > ref:
            ref = 3.0 * sd
        if not ref > 0:
            ref = 1.0
        d = abs(fx - th) / ref
        if math.isnan(d):
            return math.nan
        worst = max(worst, d)
    return worst


@dataclass(frozen=True)
class ParameterEstimate:
    """One physical parameter: float reference, fixed point, standard deviation."""

    name: str
    unit: str
    effect: str
    equation: str
    description: str
    value: float
    sigma: float
    fixed: float
    #: share of the variance the ridge prior still holds (:func:`~canrls.estimation.
    #: colour.prior_share`): above :data:`~canrls.estimation.colour.MAX_PRIOR_SHARE` the
    #: data cannot tell the parameter from the others, and value and sigma are the prior's
    prior_share: float = 0.0

    @property
    def identifiable(self) -> bool:
        return self.prior_share <= MAX_PRIOR_SHARE

    def to_dict(self) -> dict[str, Any]:
        return {"value": self.value, "sigma": self.sigma, "unit": self.unit,
                "fixed": self.fixed, "effect": self.effect, "equation": self.equation,
                "description": self.description, "identifiable": self.identifiable,
                "prior_share": self.prior_share}


@dataclass(frozen=True)
class EquationFit:
    """How well one equation fits, with the final estimate over all used samples."""

    equation: str
    target: str
    unit: str
    samples: int
    residual_rms: float
    fit_percent: float
    r2: float
    target_rms: float
    online_rms: float
    divergence: float
    saturations: Mapping[str, int]
    windup_steps: int
    low_excitation: bool
    condition: float
    #: samples whose target or a column was not finite: left out, with the filter's
    #: warm-up after each (see :class:`~canrls.estimation.model.RegressorBuilder`)
    nonfinite_rows: int = 0
    #: factor the residual's colour puts on the variances (kappa >= 1; the sigmas
    #: reported are multiplied by its square root; :mod:`canrls.estimation.colour`)
    sigma_inflation: float = 1.0

    def to_dict(self) -> dict[str, Any]:
        return {"equation": self.equation, "target": self.target, "unit": self.unit,
                "samples": self.samples, "residual_rms": self.residual_rms,
                "fit_percent": self.fit_percent, "r2": self.r2,
                "target_rms": self.target_rms, "online_rms": self.online_rms,
                "divergence": self.divergence, "saturations": dict(self.saturations),
                "windup_steps": self.windup_steps, "low_excitation": self.low_excitation,
                "condition": self.condition, "nonfinite_rows": self.nonfinite_rows,
                "sigma_inflation": self.sigma_inflation}


@dataclass(frozen=True)
class Estimates:
    """The estimates of every parameter and the fit of every equation."""

    parameters: tuple[ParameterEstimate, ...]
    equations: tuple[EquationFit, ...]
    effects: tuple[str, ...]

    @property
    def residual_rms(self) -> float:
        """Residual RMS of the first (mechanical) equation, in its target unit."""
        return self.equations[0].residual_rms if self.equations else math.nan

    @property
    def fit_percent(self) -> float:
        return self.equations[0].fit_percent if self.equations else math.nan

    @property
    def samples(self) -> int:
        return self.equations[0].samples if self.equations else 0

    def __getitem__(self, name: str) -> ParameterEstimate:
        for p in self.parameters:
            if p.name == name:
                return p
        raise KeyError(f"no parameter {name!r} (have: {[p.name for p in self.parameters]})")

    def to_dict(self) -> dict[str, Any]:
        return {
            "effects": list(self.effects),
            "parameters": {p.name: p.to_dict() for p in self.parameters},
            "residual_rms": self.residual_rms,
            "fit_percent": self.fit_percent,
            "samples": self.samples,
            "equations": {e.equation: e.to_dict() for e in self.equations},
        }

    def format(self) -> str:
        """A text table: every parameter with float value, sigma, fixed value and unit."""
        lines = []
        w = max([len(p.name) for p in self.parameters] + [9])
        lines.append(f"{'parameter':<{w}}  {'float':>13}  {'± sigma':>11}  {'fixed':>13}  unit")
        for p in self.parameters:
            lines.append(f"{p.name:<{w}}  {p.value:>13.6g}  {p.sigma:>11.3g}  {p.fixed:>13.6g}"
                         f"  {p.unit}"
                         + ("" if p.identifiable else
                            f"  NOT IDENTIFIABLE ({100 * p.prior_share:.0f} % prior)"))
        weak = [p.name for p in self.parameters if not p.identifiable]
        if weak:
            lines.append(f"not identifiable from these data: {', '.join(weak)}: the data "
                         f"cannot tell {'them' if len(weak) > 1 else 'it'} from the other "
                         f"parameters, value and sigma are the prior's (e.g. Coulomb "
                         f"friction and an offset while the speed never reverses; "
                         f"'canrls diagnose' names the experiment)")
        for e in self.equations:
            lines.append(
                f"{e.equation}: residual RMS {e.residual_rms:.4g} {e.unit}, "
                f"fit {e.fit_percent:.2f} %,"
                f" R² {e.r2:.5f}, {e.samples} samples, fixed-vs-float divergence "
                f"{e.divergence:.2e}"
                + (f", saturations {dict(e.saturations)}" if e.saturations else "")
                + (", LOW EXCITATION" if e.low_excitation else "")
                + (f", {e.nonfinite_rows} samples with a non-finite term left out "
                   f"(with the filter's warm-up after each)" if e.nonfinite_rows else ""))
        return "\n".join(lines)

    __str__ = format


@dataclass(frozen=True)
class EquationBlock:
    """What one block did to one equation (recorded with ``record=True``).

    ``y`` and ``eps``/``eps_fixed`` are in the target unit; ``theta``/``theta_fixed``
    are physical parameters after each sample; ``used`` marks the rows that updated
    the estimators (not in a warm-up).
    """

    equation: str
    t: F64
    y: F64
    eps: F64
    eps_fixed: F64
    used: npt.NDArray[np.bool_]
    online_rms: F64
    flags: npt.NDArray[np.uint8]
    theta: F64 | None
    theta_fixed: F64 | None
    phi: F64 | None


@dataclass(frozen=True)
class PipelineBlock:
    """Per-equation results of one :meth:`Pipeline.process` call."""

    samples: int
    equations: tuple[EquationBlock, ...]


# ----------------------------------------------------------------------- estimator
class EquationEstimator:
    """Builder, float RLS, fixed RLS and statistics of one equation."""

    def __init__(self, equation: Equation, dt: float, settings: EstimatorSettings,
                 energy: npt.ArrayLike | None = None) -> None:
        self.equation = equation
        self.settings = settings
        self.dt = float(dt)
        self.builder = equation.builder(dt)
        n = equation.n
        s = settings
        #: ridge weight of each column, alpha_j = alpha * e_j (EstimatorSettings.ridge)
        self.ridge = s.ridge(n, energy)
        self.rls = RLS(n, lam=s.lam, alpha=self.ridge, trace_max=s.trace_max)
        self.fixed_config = s.fixed_config(n, self.ridge)
        self.frls = FixedRLS(self.fixed_config, n, lam=s.lam, alpha=self.ridge,
                             trace_max=s.trace_max)
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

        return EquationBlock(
            equation=out.equation, t=out.t[real], y=out.y[real], eps=out.eps[real],
            eps_fixed=out.eps_fixed[real], used=out.used[real],
            online_rms=out.online_rms[real], flags=out.flags[real],
            theta=pick(out.theta), theta_fixed=pick(out.theta_fixed), phi=pick(out.phi))

    def _regressors(self, signals: Signals, restart: npt.NDArray[np.bool_], restarts: int
                    ) -> tuple[F64, F64, npt.NDArray[np.bool_] | None]:
        """(phi, y, rows with a non-finite value or None) of the block, the filter
        restarted at the ``restart`` rows."""
        N = len(restart)
        if restarts == 0 or (restarts == 1 and restart[0]):
            # one piece (the common case): no slicing, no joining
            if restarts:
                self.builder.reset()
            phi, y, _, nonfinite = self.builder.regressors(signals)
            return phi, y, nonfinite
        # the filter restarts at every gap (and at the start): split the block there
        bounds = [int(k) for k in np.flatnonzero(restart)] + [N]
        if bounds[0] != 0:
            bounds.insert(0, 0)
        parts = []
        for a, b in zip(bounds[:-1], bounds[1:], strict=True):
            if restart[a]:
                self.builder.reset()
            parts.append(self.builder.process(signals.slice(a, b)))
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
        restart, use, restarts, used = sel.restart, sel.use, sel.restarts, sel.used
        if real is not None or settling is not None:
            if real is not None:
                use &= real
            if settling is not None:
                use &= ~settling
            used = int(np.count_nonzero(use))
        phi, y, nonfinite = self._regressors(signals, restart, restarts)
        if nonfinite is not None or self._since_nonfinite <= self.warmup:
            self._skip_nonfinite(nonfinite, use)
            used = int(np.count_nonzero(use))
        # the used rows (None: all of them, or none)
        rows = np.flatnonzero(use) if 0 < used < N else None
        if used:
            phi_u = phi if rows is None else phi[rows]
            y_u = y if rows is None else y[rows]
            # on a large block the fixed-point estimator runs in a thread meanwhile: the
            # two share no state, and their kernels release the GIL
            fixed = Background(self._fixed_block, phi_u, y_u, record,
                               name="canrls fixed point") if used >= OVERLAP_ROWS else None
            try:
                eps_u, theta_u, _, flags_u, _ = self.rls.run_block(phi_u, y_u, record)
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
        y_out = np.empty(N)
        eps = np.empty(N)
        eps_fixed = np.empty(N)
        flags = np.empty(N, np.uint8)
        rms = np.empty(N)
        # after the estimators, row by row in C (canrls._kernels.bookkeeping): spread the
        # used rows' errors (the fixed-point one is epsq * lsb, exact) and flags over the
        # block, 0 elsewhere; the residual mean square r <- r + beta (eps^2 - r) on used
        # rows; y, the errors and sqrt(r) in the target unit (x 2**s_y, one rounding);
        # the sums M += phi phi' (upper triangle), v += phi y, s += [1, y, y^2]
        self.windup_steps += _kernels.bookkeeping(
            phi, y, use, eps_u, epsq_u, self.fixed_config.eps.lsb, flags_u, flagsq_u,
            self._M, self._v, self._s, self.beta, self._rms_state, eq.scaling.target,
            y_out, eps, eps_fixed, flags, rms)
        theta = theta_fixed = None
        if record:
            # rows in a warm-up did not update: they stay nan
            theta = np.full((N, eq.n), np.nan)
            theta_fixed = np.full((N, eq.n), np.nan)
            if theta_u is not None and thetaq_u is not None:
                at = slice(None) if rows is None else rows
                theta[at] = eq.to_physical(theta_u)
                theta_fixed[at] = eq.to_physical(self.frls.config.theta.to_float(thetaq_u))
        return EquationBlock(
            equation=eq.name, t=t, y=y_out, eps=eps, eps_fixed=eps_fixed, used=use,
            online_rms=rms, flags=flags, theta=theta, theta_fixed=theta_fixed,
            phi=phi if record else None)

    # -- results ----------------------------------------------------------------------
    @property
    def samples(self) -> int:
        return int(self._s[0])

    def residual_stats(self, theta_norm: F64 | None = None) -> tuple[float, float, float, float]:
        """(residual RMS, fit %, R², target RMS) of ``theta_norm`` (default: the float estimate)."""
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
        scale = math.ldexp(1.0, eq.scaling.target)
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
        # sigma = sqrt(kappa sigma^2 diag P): the RLS formula, widened by the colour
        sigma = eq.sigma_to_physical(self.rls.std() * math.sqrt(self.sigma_inflation()))
        fixed = eq.to_physical(self.frls.theta_float)
        share = prior_share(self.rls.P, self.rls.ridge)
        return [ParameterEstimate(p.name, p.unit, p.effect, eq.name, p.description, v, s, f,
                                  float(sh))
                for p, v, s, f, sh in zip(eq.parameters, value.tolist(), sigma.tolist(),
                                          fixed.tolist(), share.tolist(), strict=True)]

    def estimates(self) -> tuple[list[ParameterEstimate], EquationFit]:
        eq = self.equation
        params = self.parameters()
        rms, fit, r2, trms = self.residual_stats()
        exc = self.rls.excitation()
        fit_obj = EquationFit(
            equation=eq.name, target=eq.target.description, unit=eq.target.unit,
            samples=self.samples, residual_rms=rms, fit_percent=fit, r2=r2,
            target_rms=trms,
            online_rms=math.sqrt(self._rms_state[0]) * math.ldexp(1.0, eq.scaling.target),
            divergence=self.divergence(), saturations=self.frls.saturations.nonzero(),
            windup_steps=self.windup_steps, low_excitation=bool(exc.low),
            condition=float(exc.cond), nonfinite_rows=self.nonfinite_rows,
            sigma_inflation=self.sigma_inflation())
        return params, fit_obj

    def sigma_inflation(self) -> float:
        """``kappa`` of the current float estimate (:class:`ResidualTail`)."""
        return self.tail.inflation(np.asarray(self.rls.theta, dtype=np.float64))

    def state(self) -> dict[str, Any]:
        return {"rls": self.rls.state(), "fixed": self.frls.state(), "M": self._M.copy(),
                "v": self._v.copy(), "s": self._s.copy(), "rms": self._rms_state.copy(),
                "windup_steps": self.windup_steps, "nonfinite_rows": self.nonfinite_rows,
                "tail": self.tail.state()}

    def restore(self, d: Mapping[str, Any]) -> None:
        """Continue from :meth:`state` (the filter restarts: the next samples warm it up)."""
        self.rls = RLS.from_state(d["rls"])
        self.frls = FixedRLS.from_state(d["fixed"])
        self.fixed_config = self.frls.config  # the formats the restored state is in
        self._M = np.array(d["M"], dtype=np.float64)
        self._v = np.array(d["v"], dtype=np.float64)
        self._s = np.array(d["s"], dtype=np.float64)
        self._rms_state = np.array(d["rms"], dtype=np.float64)
        self.windup_steps = int(d["windup_steps"])
        self.nonfinite_rows = int(d.get("nonfinite_rows", 0))
        self._since_nonfinite = self.warmup + 1
        if "tail" in d:
            self.tail.restore(d["tail"])
        self.builder.reset()
        self.selector.reset()
        self.filler.reset()


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
    """

    def __init__(self, model: Model, dt: float, settings: EstimatorSettings | None = None,
                 energy: Mapping[str, npt.ArrayLike] | None = None) -> None:
        if not (dt > 0 and math.isfinite(dt)):
            raise ConfigError(f"sample period dt = {dt!r}: must be > 0")
        self.model = model
        self.dt = float(dt)
        self.settings = settings or EstimatorSettings()
        self.energy = None if energy is None else {
            k: np.asarray(v, dtype=np.float64).copy() for k, v in energy.items()}
        self.estimators = tuple(
            EquationEstimator(eq, self.dt, self.settings,
                              None if energy is None else energy[eq.name])
            for eq in model.equations)
        self.samples = 0

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
        return Estimates(tuple(params), tuple(fits), self.model.effect_names)

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
        """Change the forgetting factor of both estimators (validated)."""
        if not (0.5 < lam <= 1.0):
            raise ConfigError(f"lambda = {lam!r}: must be in (0.5, 1]")
        for e in self.estimators:
            e.rls.set_lambda(lam)
            e.frls.set_lambda(lam)

    def with_model(self, model: Model, warm: bool = True,
                   energy: Mapping[str, npt.ArrayLike] | None = None) -> Pipeline:
        """A new pipeline for ``model`` (e.g. an effect added or removed).

        With ``warm`` (default) the parameters both models share start from their
        current estimates (float and fixed point alike) instead of zero, so adding an
        effect does not make the others converge again; the covariance restarts from
        the prior for every parameter, so all of them adapt. ``energy``: the new
        model's column energies (as for :class:`Pipeline`).
        """
        new = Pipeline(model, self.dt, self.settings, energy)
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
