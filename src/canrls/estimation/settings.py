"""The estimator's settings (:class:`EstimatorSettings`) and the limits of the
normalisation and of the ridge prior that the pipeline and the front end share."""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from canrls.core.checks import MAX_TIMESTAMP, check_lambda, in_range, is_positive
from canrls.core.errors import ConfigError, FixedPointError
from canrls.estimation.fixed.estimator import FixedRLS
from canrls.estimation.fixed.formats import WORD_LIMITS, FixedConfig, QFormat, word_problem

__all__ = [
    "ALPHA_MAX",
    "ALPHA_MIN",
    "ENERGY_FLOOR",
    "MIN_ENERGY",
    "RESCALE_HEADROOM",
    "RESCALE_LIMIT",
    "RMS_HEADROOM",
    "EstimatorSettings",
    "exponent_for",
]

F64 = npt.NDArray[np.float64]

#: Smallest column energy (mean square, normalised units) the ridge is scaled with: a
#: column with less on the calibration window was not excited there, and its prior
#: then weighs as for a column at 2**-10 of full scale (P0 = 2**20/alpha, which the
#: fixed-point formats still hold for up to 12 columns).
ENERGY_FLOOR = 2.0 ** -20
#: Smallest energy (normalised mean square) a column's prior is scaled with: a column
#: with an RMS of 1/32 of full scale, the least the calibration's RMS rule gives a
#: data-scaled column; a column bounded by its own function that the window barely
#: excites and a pending one until it is seen take it. It bounds P0 by 2**10/alpha,
#: which the fixed-point formats hold.
MIN_ENERGY = 2.0 ** -10
#: The calibration puts the window's RMS of each data-scaled column (and the first value
#: of a pending one) at most 1/RMS_HEADROOM of full scale (:func:`exponent_for`): room
#: for crest factors and growth, normalised energies in (2**-10, 2**-8].
RMS_HEADROOM = 16.0
#: A used row whose normalised value of a data-scaled column (or of the output) exceeds
#: this in magnitude has outgrown its exponent: the estimator rescales it first, exactly.
RESCALE_LIMIT = 1.0
#: After a rescale, the value that asked for it is at most 1/RESCALE_HEADROOM of full scale.
RESCALE_HEADROOM = 4.0


def exponent_for(x: float, headroom: float) -> int:
    """The smallest ``s`` with ``headroom * |x| <= 2**s`` (``x`` finite, not zero)."""
    m, e = math.frexp(headroom * abs(x))
    return e - 1 if m == 0.5 else e


#: The ridge weight ``alpha`` (the prior weighs like ``alpha`` samples of each column)
#: from one billionth of a sample to a billion samples. Within it, the fixed-point words
#: set the lower end: P0 = diag(1/(alpha e_j)) must have a Q format
#: (:meth:`EstimatorSettings.fixed_config` names the smallest alpha that has one).
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
        square :math:`\\bar e_j` on the calibration window,
        :class:`~canrls.estimation.pipeline.Pipeline`); without column energies,
        :math:`P_0 = I/\\alpha` in normalised units
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
        check_lambda(self.lam, "estimator.lambda")
        if not is_positive(self.alpha):
            raise ConfigError(f"estimator.alpha = {self.alpha!r}: must be > 0")
        if not in_range(self.alpha, ALPHA_MIN, ALPHA_MAX):
            # P0 = diag(1 / (alpha e_j)), 2**-10 <= e_j <= 1: beyond these the fixed-point
            # format of P has no exponent for P0 (and the prior means nothing or all)
            raise ConfigError(f"estimator.alpha = {self.alpha!r}: must be from {ALPHA_MIN:g} "
                              f"to {ALPHA_MAX:g} (the prior weighs like alpha samples of "
                              f"each column)")
        if self.warmup_s is not None and not in_range(self.warmup_s, 0.0, math.inf,
                                                      hi_open=True):
            raise ConfigError(f"estimator.warmup_s = {self.warmup_s!r}: must be >= 0 seconds")
        if not in_range(self.gap_periods, 1.0, math.inf, lo_open=True, hi_open=True):
            raise ConfigError(f"estimator.gap_periods = {self.gap_periods!r}: must be a "
                              f"finite number > 1")
        if not (self.max_phase_step == math.inf or is_positive(self.max_phase_step)):
            raise ConfigError(f"estimator.max_phase_step = {self.max_phase_step!r}: must be > 0 "
                              f"(inf: no limit)")
        if not is_positive(self.rms_time_s):
            raise ConfigError(f"estimator.rms_time_s = {self.rms_time_s!r}: must be a finite "
                              f"number > 0 seconds")
        if not in_range(self.calibration_s, 0.0, MAX_TIMESTAMP, lo_open=True):
            # a window longer than any log's times calibrates on the whole log already
            raise ConfigError(f"estimator.calibration_s = {self.calibration_s!r}: must be "
                              f"> 0 seconds, at most {MAX_TIMESTAMP:g}")
        for name in WORD_LIMITS:
            v = getattr(self, name)
            if v is not None and (why := word_problem(name, v)) is not None:
                raise ConfigError(f"fixed.{name} = {v!r}: {why}")
        if not is_positive(self.theta_max):
            raise ConfigError(f"fixed.theta_max = {self.theta_max!r}: must be a positive "
                              f"number")
        try:  # the Q format of theta, as FixedConfig.auto makes it
            QFormat.for_range(self.theta_max, self.word_bits)
        except FixedPointError as e:
            raise ConfigError(f"fixed.theta_max = {self.theta_max!r}: no Q format of "
                              f"{self.word_bits}-bit words holds it ({e})") from e

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
        weights :math:`\alpha_j`, default ``alpha`` for all, before the calibration).

        The lower limit of ``alpha`` that ``--alpha``'s help states: P0 = diag(1/(alpha
        e_j)) must have Q formats. Before the calibration it is checked with every
        column at :data:`MIN_ENERGY`, the least energy a calibration gives (so the same
        alpha is refused for any log, live or offline; with Q formats set in the
        configuration, at the energies), after it at the energies found.

        :raises FixedPointError: no Q formats; when a larger ``alpha`` would give them,
            the message names the smallest.
        """
        if ridge is None:  # a function of these settings and n alone: found once
            got = self._uncalibrated.get(n)
            if got is None:
                flat = np.full(n, float(self.alpha))
                if not self.fixed_overrides:  # formats a user set are checked as they are
                    self._formats(n, flat * MIN_ENERGY)  # the calibrated prior at its largest
                got = self._uncalibrated[n] = self._formats(n, flat)
            return got
        return self._formats(n, np.asarray(ridge, dtype=np.float64))

    @functools.cached_property
    def _uncalibrated(self) -> dict[int, FixedConfig]:
        """:meth:`fixed_config` before the calibration, by ``n`` (every stream's first
        pipelines ask for it again)."""
        return {}

    def _formats(self, n: int, ridge: F64) -> FixedConfig:
        """:meth:`_auto`, its error naming the smallest alpha when alpha is the cause."""
        try:
            return self._auto(n, ridge)
        except FixedPointError as e:
            smallest = self._smallest_alpha(n, ridge)
            if smallest is None:  # not the prior's size: the formats say what
                raise
            raise FixedPointError(
                f"estimator.alpha = {self.alpha!r}: too small for the fixed-point words: "
                f"the smallest is {smallest:.2g} here (P0 = diag(1/(alpha e_j)) of these "
                f"{n} parameters needs a Q format in {self.word_bits}-bit words; or raise "
                f"fixed.word_bits): {e}") from e

    def _auto(self, n: int, ridge: npt.ArrayLike) -> FixedConfig:
        """:meth:`FixedConfig.auto`, checked by building the kernel it plans (P0 and the
        plan's shifts are limits of the formats too)."""
        cfg = FixedConfig.auto(n, ridge, self.lam, theta_max=self.theta_max,
                               word_bits=self.word_bits, acc_bits=self.acc_bits,
                               input_bits=self.input_bits, trace_max=self.trace_max,
                               # mypy cannot tell these keys (format names: P, theta,
                               # ...) from auto's named arguments
                               **dict(self.fixed_overrides))  # type: ignore[arg-type]
        FixedRLS(cfg, n, lam=self.lam, alpha=ridge, trace_max=self.trace_max)
        return cfg

    def _smallest_alpha(self, n: int, ridge: F64) -> float | None:
        """The smallest ``alpha`` (two significant digits, rounded up) whose ridge, in
        proportion to ``ridge``, has Q formats; None when not even :data:`ALPHA_MAX` has."""
        def fits(alpha: float) -> bool:
            try:
                self._auto(n, ridge * (alpha / float(self.alpha)))
            except FixedPointError:
                return False
            return True

        lo, hi = math.log(float(self.alpha)), math.log(ALPHA_MAX)
        if not fits(ALPHA_MAX):
            return None
        for _ in range(60):  # bisection in log alpha: the formats grow with 1/alpha
            mid = 0.5 * (lo + hi)
            lo, hi = (lo, mid) if fits(math.exp(mid)) else (mid, hi)
        smallest = math.exp(hi)
        shown = float(f"{smallest:.1e}")
        while shown < smallest or not fits(shown):
            shown = float(f"{shown + 10 ** (math.floor(math.log10(shown)) - 1):.1e}")
        return shown
