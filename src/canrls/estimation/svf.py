r"""State-variable filter: the low-pass ``F(s)`` and its derivative ``s F(s)``.

Every regression equation of canrls is filtered by the same second-order low pass
:math:`F(s) = \omega_c^2/(s^2 + 2\zeta\omega_c s + \omega_c^2)`, realised as a two-state
system whose states are ``x1 = F[u]`` and ``x2 = sF[u]``: the filtered signal and its
filtered derivative, without differentiating a noisy measurement. :class:`SVF` runs it,
discretised exactly for each column's hold, in the C kernel ``canrls._kernels.svf``;
:func:`gain_bounds` bounds its outputs for the normalisation. The discretisation, the
holds, the choice of the cutoff and the bounds are in docs/effects.md, *The
state-variable filter*.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Literal

import numpy as np
import numpy.typing as npt

from canrls import _kernels
from canrls.core.checks import in_range
from canrls.core.errors import ConfigError

__all__ = ["SVF", "gain_bounds", "DEFAULT_CUTOFF_HZ", "DEFAULT_ZETA", "ZETA_RANGE",
           "MAX_TIME_CONSTANT"]

F64 = npt.NDArray[np.float64]

#: Default cutoff frequency [Hz] (suits a 1 kHz control rate).
DEFAULT_CUTOFF_HZ = 25.0
#: Default damping ratio (Butterworth).
DEFAULT_ZETA = 0.7071

#: Damping ratios the filter accepts: far outside, the poles' arithmetic cancels
#: (``zeta - sqrt(zeta^2 - 1)`` is 0 in float64 at ``zeta = 1e8``) and the filter is useless.
ZETA_RANGE = (0.05, 10.0)
#: Longest time constant ``1 / (zeta w_c)`` of the filter, in samples: the warm-up (5 of
#: them) and the residual's colour window (64 warm-ups) are sized by it, so a cutoff far
#: below the sample rate (1e-300 Hz) would ask for arrays larger than any memory.
MAX_TIME_CONSTANT = 5000

Hold = Literal["foh", "zoh"]


def _check_positive(name: str, value: float) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError) as e:
        raise ConfigError(f"SVF {name} = {value!r}: not a number") from e
    if not math.isfinite(v) or v <= 0.0:
        raise ConfigError(f"SVF {name} = {value!r}: must be a finite number > 0")
    return v


def _check_zeta(zeta: float) -> float:
    z = _check_positive("zeta", zeta)
    if not in_range(z, *ZETA_RANGE):
        raise ConfigError(f"SVF zeta = {zeta!r}: the damping ratio must be in "
                          f"[{ZETA_RANGE[0]:g}, {ZETA_RANGE[1]:g}]")
    return z


def gain_bounds(cutoff_hz: float, zeta: float = DEFAULT_ZETA) -> tuple[float, float]:
    r"""Return ``(F_GAIN, SF_GAIN)``: the L1 norms of the impulse responses of ``F`` and ``sF``.

    ``|F[u] - c| <= F_GAIN * h`` and ``|sF[u]| <= SF_GAIN * h`` for an input within
    ``c +- h``. ``F_GAIN`` is dimensionless, ``SF_GAIN`` is in 1/s.
    """
    wc = 2.0 * math.pi * _check_positive("cutoff_hz", cutoff_hz)
    z = _check_zeta(zeta)
    if z < 1.0:
        sq = math.sqrt(1.0 - z * z)
        # r = exp(-zeta pi / sqrt(1 - zeta^2)): ratio of successive extrema of f
        r = math.exp(-z * math.pi / sq)
        # ||f||_1 = sum over half periods of |step(t_{n+1}) - step(t_n)| = (1 + r) / (1 - r)
        f_gain = (1.0 + r) / (1.0 - r)
        # extrema of f at t_n = (acos(zeta) + n pi) / w_d, |f(t_n)| = w_c exp(-zeta w_c t_n)
        sf_gain = 2.0 * wc * math.exp(-z * math.acos(z) / sq) / (1.0 - r)
        return f_gain, sf_gain
    if z == 1.0:
        # f = w_c^2 t exp(-w_c t), peak w_c / e at t = 1 / w_c
        return 1.0, 2.0 * wc / math.e
    sq = math.sqrt(z * z - 1.0)
    p1 = -wc * (z - sq)  # slow pole
    p2 = -wc * (z + sq)  # fast pole
    t_peak = math.log(p2 / p1) / (p1 - p2)
    peak = wc / (2.0 * sq) * (math.exp(p1 * t_peak) - math.exp(p2 * t_peak))
    return 1.0, 2.0 * peak


def _expm_2x2(wc: float, zeta: float, dt: float) -> F64:
    r"""Closed-form ``expm(A dt)`` for ``A = [[0, 1], [-wc^2, -2 zeta wc]]``.

    With :math:`\mu = -\zeta\omega_c` and :math:`\delta^2 = \omega_c^2(\zeta^2 - 1)`:
    :math:`e^{A T} = e^{\mu T}\,(c\,I + s\,(A - \mu I))`, where ``c = cos(w_d T)``,
    ``s = sin(w_d T) / w_d`` (underdamped), ``c = 1, s = T`` (critical) or ``cosh``/``sinh``
    (overdamped).
    """
    mu = -zeta * wc
    if zeta < 1.0:
        wd = wc * math.sqrt(1.0 - zeta * zeta)
        c, s = math.cos(wd * dt), math.sin(wd * dt) / wd
    elif zeta == 1.0:
        c, s = 1.0, dt
    else:
        d = wc * math.sqrt(zeta * zeta - 1.0)
        c, s = math.cosh(d * dt), math.sinh(d * dt) / d
    e = math.exp(mu * dt)
    # A - mu I = [[zeta wc, 1], [-wc^2, -zeta wc]]
    return np.array([[e * (c + s * zeta * wc), e * s],
                     [-e * s * wc * wc, e * (c - s * zeta * wc)]])


def _discretise(wc: float, zeta: float, dt: float, hold: Hold) -> tuple[F64, F64, F64]:
    """Exact discretisation ``x[k] = Ad x[k-1] + G0 u[k-1] + G1 u[k]``.

    The input matrices follow from ``Ad`` through identities that hold exactly for
    this system, so the discrete filter keeps the DC gain ``F(0) = 1`` and the ramp
    response ``sF[t] = 1`` of the continuous one to the last bit that matters:

    * constant input: the steady state is ``x = e1 = [1, 0]``, so
      ``Gu = G0 + G1 = (I - Ad) e1``;
    * unit ramp ``u = t``: the steady state is ``x = t e1 + v`` with
      ``v = [-2 zeta / wc, 1]``, so the response to a ramp of slope 1 over one sample
      from 0 is ``Gw = dt e1 + (I - Ad) v``, and the straight-line (first-order) hold gives
      ``G1 = Gw / dt``, ``G0 = Gu - G1``. Zero-order hold: ``G0 = Gu``, ``G1 = 0``.
    """
    Ad = _expm_2x2(wc, zeta, dt)
    e1 = np.array([1.0, 0.0])
    eye = np.eye(2)
    Gu = (eye - Ad) @ e1
    if hold == "zoh":
        return Ad, Gu, np.zeros(2)
    v = np.array([-2.0 * zeta / wc, 1.0])
    Gw = dt * e1 + (eye - Ad) @ v
    G1 = Gw / dt
    G0 = Gu - G1
    return Ad, G0, G1


def impulse_response(cutoff_hz: float, dt: float, zeta: float, hold: Hold
                     ) -> tuple[F64, F64]:
    """``(F, sF)``: the filter's responses to a unit sample at rest, long enough to decay
    (40 time constants): what filtered white noise is made of."""
    svf = SVF(cutoff_hz, dt, zeta, hold)
    m = int(math.ceil(40.0 / (min(svf.zeta, 1.0) * svf.wc * svf.dt))) + 8
    u = np.zeros(m + 2)
    u[2] = 1.0  # the filter starts at rest on u[0] = 0
    f, sf = svf.process(u)
    return f[2:].copy(), sf[2:].copy()


class SVF:
    r"""Second-order state-variable filter applied column-wise with carried state.

    :param cutoff_hz: cutoff frequency :math:`f_c` [Hz], ``0 < f_c < 1/(2 dt)``.
    :param dt: sample period [s].
    :param zeta: damping ratio :math:`\zeta` in :data:`ZETA_RANGE`.
    :param hold: ``"foh"`` (straight line between samples, default) or ``"zoh"`` for every
        column, or a sequence with one of them per column (the column count is then
        fixed to its length).
    :raises ConfigError: a parameter is not a positive finite number, the cutoff is not
        below Nyquist or so low that the filter's time constant exceeds
        :data:`MAX_TIME_CONSTANT` samples, ``zeta`` is outside :data:`ZETA_RANGE`, or a
        hold is unknown.

    The state is created on the first call to :meth:`process` (its column count is then
    fixed) and carried to the next call; :meth:`reset` forgets it.
    """

    def __init__(self, cutoff_hz: float = DEFAULT_CUTOFF_HZ, dt: float = 1e-3,
                 zeta: float = DEFAULT_ZETA, hold: Hold | Sequence[Hold] = "foh") -> None:
        self.cutoff_hz = _check_positive("cutoff_hz", cutoff_hz)
        self.dt = _check_positive("dt", dt)
        self.zeta = _check_zeta(zeta)
        holds = (hold,) if isinstance(hold, str) else tuple(hold)
        for h in holds:
            if h not in ("foh", "zoh"):
                raise ConfigError(f"SVF hold = {h!r}: must be 'foh' or 'zoh'")
        #: The hold of every column (a string) or of each column (a tuple).
        self.hold: Hold | tuple[Hold, ...] = hold if isinstance(hold, str) else holds
        nyquist = 0.5 / self.dt
        if self.cutoff_hz >= nyquist:
            raise ConfigError(
                f"SVF cutoff_hz = {cutoff_hz!r}: must be below the Nyquist frequency "
                f"{nyquist:g} Hz (dt = {dt!r} s)")
        # tau = 1 / (zeta w_c), in samples
        tau = 1.0 / (self.zeta * 2.0 * math.pi * self.cutoff_hz * self.dt)
        if not tau <= MAX_TIME_CONSTANT:
            low = 1.0 / (self.zeta * 2.0 * math.pi * MAX_TIME_CONSTANT * self.dt)
            raise ConfigError(
                f"SVF cutoff_hz = {cutoff_hz!r}: too low for dt = {dt!r} s, the filter "
                f"would remember {tau:.3g} samples (at most {MAX_TIME_CONSTANT}: cutoff_hz "
                f">= {low:.3g} Hz)")
        #: Cutoff angular frequency w_c [rad/s].
        self.wc = 2.0 * math.pi * self.cutoff_hz
        self.Ad, g0f, g1f = _discretise(self.wc, self.zeta, self.dt, "foh")
        _, g0z, g1z = _discretise(self.wc, self.zeta, self.dt, "zoh")
        self._coef: dict[str, tuple[F64, F64]] = {"foh": (g0f, g1f), "zoh": (g0z, g1z)}
        #: L1 bounds of F (dimensionless) and sF [1/s], see :func:`gain_bounds`.
        self.f_gain, self.sf_gain = gain_bounds(self.cutoff_hz, self.zeta)
        self._x1: F64 | None = None
        self._x2: F64 | None = None
        self._up: F64 | None = None
        self._G0: F64 | None = None
        self._G1: F64 | None = None
        self._primed = np.zeros(1, dtype=np.int64)

    def __repr__(self) -> str:
        return (f"SVF(cutoff_hz={self.cutoff_hz!r}, dt={self.dt!r}, zeta={self.zeta!r}, "
                f"hold={self.hold!r})")

    def coefficients(self, hold: Hold = "foh") -> tuple[F64, F64]:
        """``(G0, G1)`` of a hold: ``x[k] = Ad x[k-1] + G0 u[k-1] + G1 u[k]``."""
        g0, g1 = self._coef[hold]
        return g0.copy(), g1.copy()

    @property
    def G0(self) -> F64:
        """``G0`` of a single hold (2,), or per column (m, 2) for a sequence of holds."""
        if isinstance(self.hold, str):
            return self.coefficients(self.hold)[0]
        return np.array([self._coef[h][0] for h in self.hold])

    @property
    def G1(self) -> F64:
        """``G1`` of a single hold (2,), or per column (m, 2) for a sequence of holds."""
        if isinstance(self.hold, str):
            return self.coefficients(self.hold)[1]
        return np.array([self._coef[h][1] for h in self.hold])

    @property
    def settling_time(self) -> float:
        """About four time constants of the slowest pole [s]: the transient to discard."""
        if self.zeta <= 1.0:
            return 4.0 / (self.zeta * self.wc)
        return 4.0 / (self.wc * (self.zeta - math.sqrt(self.zeta**2 - 1.0)))

    @property
    def state(self) -> tuple[F64, F64] | None:
        """Copies of ``(x1, x2)`` per column, or ``None`` before the first sample."""
        if self._x1 is None or self._x2 is None or self._primed[0] == 0:
            return None
        return self._x1.copy(), self._x2.copy()

    def reset(self) -> None:
        """Forget the state: the next sample starts the filter at rest again."""
        self._x1 = self._x2 = self._up = None
        if isinstance(self.hold, str):
            self._G0 = self._G1 = None
        self._primed[0] = 0

    def process(self, u: npt.ArrayLike) -> tuple[F64, F64]:
        """Filter a block; return ``(F[u], sF[u])`` with the shape of ``u``.

        ``u`` is ``(N,)`` (one column) or ``(N, m)`` (``m`` columns filtered
        independently). The column count must not change between calls.
        """
        a = np.asarray(u, dtype=np.float64)
        one_d = a.ndim == 1
        if one_d:
            a = a.reshape(-1, 1)
        if a.ndim != 2:
            raise ValueError(f"SVF.process: expected a 1-D or 2-D array, got shape {a.shape}")
        a = np.ascontiguousarray(a)
        G0, G1, x1, x2, up = self._prepare(a.shape[1])
        f = np.empty_like(a)
        sf = np.empty_like(a)
        _kernels.svf(a, self.Ad, G0, G1, x1, x2, up, self._primed, f, sf)
        if one_d:
            return f[:, 0], sf[:, 0]
        return f, sf

    def _prepare(self, m: int) -> tuple[F64, F64, F64, F64, F64]:
        """Coefficients and state for ``m`` columns (created on the first call): the
        kernel's ``G0, G1, x1, x2, up``."""
        G0, G1 = self._G0, self._G1
        if G0 is None or G1 is None:
            holds = [self.hold] * m if isinstance(self.hold, str) else list(self.hold)
            if len(holds) != m:
                raise ValueError(f"SVF.process: got {m} columns, the filter has "
                                 f"{len(holds)} holds")
            self._G0 = G0 = np.ascontiguousarray([self._coef[h][0] for h in holds])
            self._G1 = G1 = np.ascontiguousarray([self._coef[h][1] for h in holds])
        x1, x2, up = self._x1, self._x2, self._up
        if x1 is None or x2 is None or up is None:
            if G0.shape[0] != m:
                raise ValueError(f"SVF.process: got {m} columns, the filter has "
                                 f"{G0.shape[0]}")
            self._x1 = x1 = np.zeros(m)
            self._x2 = x2 = np.zeros(m)
            self._up = up = np.zeros(m)
        elif x1.shape[0] != m:
            raise ValueError(
                f"SVF.process: got {m} columns, the filter state has {x1.shape[0]}")
        return G0, G1, x1, x2, up

    def process_scaled(self, u: F64, derivative: npt.NDArray[np.bool_], scale: F64,
                        y: F64, phi: F64) -> None:
        """:meth:`process` for the regressors, fused: column ``j`` of ``u`` (N, m) gives
        ``sF[u_j]`` where ``derivative[j]`` else ``F[u_j]``, times ``scale[j]``; column 0
        goes to ``y`` (N,), the others to ``phi`` (N, m-1). The same arithmetic and state
        as :meth:`process` (``scale`` holds exact powers of two).
        """
        a = np.ascontiguousarray(u, dtype=np.float64)
        G0, G1, x1, x2, up = self._prepare(a.shape[1])
        _kernels.svf_scaled(a, self.Ad, G0, G1, x1, x2, up, self._primed, derivative, scale,
                            y, phi)
