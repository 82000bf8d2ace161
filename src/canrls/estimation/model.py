r"""The identification model: which effects, which equations, which regressors.

A :class:`Model` holds the axis, the target, the effects and their options, the
state-variable filter settings, the user terms and the signal ranges. It is validated
once, when built, and then yields its :class:`Equation`\ s: the mechanical one
(whenever a mechanical effect is present) and the electrical one (when ``electrical``
is). Each equation knows its parameters and builds the regressors the estimators
consume, through a stateful :class:`RegressorBuilder`.

Configuration (TOML, the ``[model]`` table)
-------------------------------------------
.. code-block:: toml

    [model]
    axis = "rotary"            # "rotary" (rad, rad/s, N·m) or "linear" (m, m/s, N)
                               # (canrls fit/diagnose/run: default from the DBC units)
    pitch = 1.0                # linear only: metres per period of unbalance/cogging terms
                               # (default: scaled from the data, see DATA_OPTIONS)
    wrap = 0.2                 # linear only, optional: position wraps with this period [m]
    kt = 0.12                  # optional: Kt [N·m/A] (linear Kf [N/A]); without it the
                               # mechanical target is the current and parameters read A
    target = "torque"          # the mechanical target: "current" (Kt*i, or i without kt)
                               # or "torque", the torque [N·m] (force [N]) the drive
                               # reports; canrls fit/diagnose/run: "torque" when the
                               # mapping has a torque signal; no kt with "torque"
    effects = ["inertia", "viscous", "coulomb", "cogging:24", "user:drag"]

    [model.filter]
    cutoff_hz = 25.0           # SVF cutoff, 0 < cutoff_hz < sample rate / 2
    zeta = 0.7071              # SVF damping
    held = ["voltage"]         # signals whose sample k is applied over [t_k, t_k + dt)
                               # (zero-order hold); the others are samples of continuous
                               # quantities (straight-line hold). See "Holds" below.

    [model.coulomb]
    band = 0.01                # smoothing band of sgn_e (Coulomb and Stribeck) [rad/s, m/s]
                               # (default: twice the measured speed noise, DATA_OPTIONS)

    [model.stribeck]
    speed = 1.0                # Stribeck speed ws [rad/s, m/s] (default: from the data)

    [[model.terms]]
    name = "drag"              # used as user:drag
    expr = "omega * abs(omega)"
    unit = "rad²/s²"           # unit of the expression's value (default "1")
    equation = "mechanical"    # or "electrical"
    range = [-1e4, 1e4]        # optional: [lo, hi] of the expression, for normalisation

    [model.ranges]             # [lo, hi] of the signals, for normalisation
    current = [-10.0, 10.0]    # A      (default [-10, 10])
    speed = [-100.0, 100.0]    # rad/s  (default [-100, 100], linear [-1, 1] m/s)
    voltage = [-50.0, 50.0]    # V      (default [-50, 50])
    position = [-1.0, 1.0]     # optional, only used to bound user terms
    acceleration = [-500.0, 500.0]  # optional [rad/s², m/s²]: tightens the inertia column
    current_rate = [-1e4, 1e4]      # optional [A/s]: tightens the inductance column
    torque = [-10.0, 10.0]     # N·m (linear: N), a torque-reporting drive's target

Every key is checked; an unknown key, a wrong type or a bad value raises
:class:`~canrls.errors.ConfigError` (an unknown or unusable effect
:class:`~canrls.errors.EffectError`) naming the file, the key and the value.

Regressors
----------
For an equation ``y = sum_j theta_j phi_j``, the builder computes per sample the raw
target (``Kt*i``, ``i``, the reported torque ``T`` or ``u``) and raw columns (value
columns, or the signal a derivative column differentiates), filters all of them with one
SVF (value columns and target through ``F``, derivative columns through ``sF``) and
scales them by exact powers of two: ``phi_j = F[.] * 2**-s_j``,
``y = F[target] * 2**-s_y``. The exponents (:attr:`Equation.scaling`) are the smallest
making the filtered signals' worst-case bound at most 1, from the ranges and the filter's
L1 gains (``canrls.estimation.svf``): a value column with raw range ``[lo, hi]`` is
bounded by ``|mid| + F_GAIN * half``, a derivative column by ``SF_GAIN * half``
(``half = (hi - lo) / 2``), or, when the range of the derivative itself is configured
(``acceleration``, ``current_rate``), by the smaller of that and the value bound of the
derivative's range. The physical parameters are ``theta_phys_j = theta_j * 2**(s_y - s_j)``
(:meth:`Equation.to_physical`).

Holds
-----
The SVF reconstructs each signal between samples before filtering it
(:mod:`canrls.estimation.svf`). A *held* signal is constant over ``[t_k, t_k + dt)`` (an inverter
voltage, or the current of an ideal current source such as the simulated drive without
the ``electrical`` effect: then set ``held = ["current", "voltage"]``); any other signal is
a sample of a continuous quantity and is joined by straight lines. The target and each
column are filtered with the hold of the signals they are computed from (a zero-order
hold as soon as one of them is held), which keeps the filtered equation exact; a wrong
choice misaligns target and columns by half a sample and biases the estimates.

The position is unwrapped with an integer turn count carried between blocks (rotary:
period 2 pi; linear: only when ``wrap`` is set), so every block size gives the same
regressors bit for bit.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from canrls import _kernels
from canrls.effect_names import EquationId
from canrls.errors import ConfigError, EffectError, SignalError
from canrls.estimation.effects import (
    DEFAULT_BAND,
    DEFAULT_PITCH,
    DEFAULT_STRIBECK_SPEED,
    ELECTRICAL,
    MECHANICAL,
    Axis,
    Column,
    Effect,
    Frame,
    ParameterSpec,
    UserTerm,
    parse_effect,
    target_unit,
)
from canrls.estimation.svf import (
    DEFAULT_CUTOFF_HZ,
    DEFAULT_ZETA,
    SVF,
    ZETA_RANGE,
    gain_bounds,
    impulse_response,
)

__all__ = [
    "DATA_OPTIONS",
    "Model",
    "Equation",
    "TargetSpec",
    "Scaling",
    "RegressorBlock",
    "RegressorBuilder",
    "PositionUnwrapper",
    "ParameterSpec",
    "DEFAULT_RANGES",
    "TARGETS",
]

F64 = npt.NDArray[np.float64]
Range = tuple[float, float]

#: Default signal ranges for normalisation (rotary; linear speed is [-1, 1] m/s).
#: Options that are scaled from the data when the configuration does not give them
#: (:func:`canrls.processor.data_defaults`): the Coulomb smoothing band (and with it
#: the minimum speed, 5 bands), the Stribeck speed and, on a linear axis, the pitch.
DATA_OPTIONS: tuple[str, ...] = ("coulomb_band", "stribeck_speed", "pitch")

DEFAULT_RANGES: Mapping[str, Range] = {
    "current": (-10.0, 10.0),
    "speed": (-100.0, 100.0),
    "voltage": (-50.0, 50.0),
    "torque": (-10.0, 10.0),
}
_LINEAR_SPEED: Range = (-1.0, 1.0)
_RANGE_KEYS = ("current", "speed", "voltage", "position", "acceleration", "current_rate",
               "torque")
_ALWAYS = frozenset({"t", "current", "speed"})
_MODEL_KEYS = ("axis", "pitch", "wrap", "kt", "target", "effects", "filter", "coulomb",
               "stribeck", "terms", "ranges", "scaling")
_HELD_ROLES = ("current", "speed", "position", "voltage", "torque")
#: The mechanical targets: the current (``Kt*i``, or ``i`` without ``kt``) or the torque
#: (force) the drive reports.
TARGETS = ("current", "torque")
_SUBKEYS: Mapping[str, tuple[str, ...]] = {
    "filter": ("cutoff_hz", "zeta", "held"),
    "coulomb": ("band",),
    "stribeck": ("speed",),
}


def _fmt(source: str, key: str, value: Any, problem: str) -> str:
    return f"{source}: {key} = {value!r}: {problem}"


def _number(source: str, key: str, value: Any, *, positive: bool = False,
            nonzero: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float | np.floating | np.integer):
        raise ConfigError(_fmt(source, key, value, "must be a number"))
    try:
        v = float(value)
    except OverflowError:  # an int too large for a float
        v = math.inf
    if not math.isfinite(v):
        raise ConfigError(_fmt(source, key, value, "must be finite"))
    if positive and v <= 0.0:
        raise ConfigError(_fmt(source, key, value, "must be > 0"))
    if nonzero and v == 0.0:
        raise ConfigError(_fmt(source, key, value, "must not be 0"))
    return v


def _canonical(spec: Any) -> str:
    """An effect name as :attr:`Effect.name` spells it (``" Cogging:06"`` -> ``"cogging:6"``)."""
    if isinstance(spec, Effect):
        return spec.name
    base, sep, arg = str(spec).strip().partition(":")
    arg = arg.strip()
    if base.strip().lower() == "cogging" and arg.isdigit():
        arg = str(int(arg))
    return base.strip().lower() + sep + arg


def _exponent(bound: float) -> int:
    """Smallest s with bound <= 2**s (0 for a zero bound)."""
    if bound <= 0.0:
        return 0
    m, e = math.frexp(bound)  # bound = m * 2**e, 0.5 <= m < 1
    return e - 1 if m == 0.5 else e


# ------------------------------------------------------------------------- results
@dataclass(frozen=True)
class TargetSpec:
    """The left-hand side of an equation: ``gain * signal``."""

    equation: str
    description: str
    unit: str
    signal: str
    gain: float


@dataclass(frozen=True)
class Scaling:
    """Power-of-two normalisation: ``phi_j = F[.] * 2**-columns[j]``, ``y = F[.] * 2**-target``.

    ``column_bounds`` / ``target_bound`` are the worst-case magnitudes of the filtered
    signals the exponents were chosen from.
    """

    columns: tuple[int, ...]
    target: int
    column_bounds: tuple[float, ...]
    target_bound: float

    @property
    def factors(self) -> F64:
        """``2**(s_y - s_j)``: multiply normalised parameters by these."""
        return np.ldexp(np.ones(len(self.columns)),
                        np.array([self.target - s for s in self.columns], dtype=np.int64))


@dataclass(frozen=True)
class RegressorBlock:
    """Normalised regressors of one block: ``y[k] ~ phi[k] @ theta``.

    ``phi`` is ``(N, n)`` float64, ``y`` is ``(N,)`` float64, ``t`` the sample times.
    ``nonfinite`` marks the rows where the target or a column was not finite before
    the filter (``None``: none was); see :class:`RegressorBuilder`.
    """

    phi: F64
    y: F64
    t: F64
    nonfinite: npt.NDArray[np.bool_] | None = None

    def __len__(self) -> int:
        return len(self.y)


class PositionUnwrapper:
    """Unwrap a wrapping position with an integer turn count carried between blocks.

    A step larger than half a period between consecutive samples counts as a wrap.
    ``period=None`` passes positions through unchanged.

    Per sample, in C (``canrls._kernels.unwrap``): ``d = p[k] - p[k-1]``; if ``d`` is
    finite, ``turns -= rint(d / period)`` (one wrap per half-period jump, opposite to
    the jump); ``theta[k] = p[k] + turns * period`` (the turns exact integers, so the
    result does not depend on the blocks).
    """

    def __init__(self, period: float | None) -> None:
        self.period = period
        self.turns = 0
        self._last: float | None = None

    def reset(self) -> None:
        self.turns = 0
        self._last = None

    def process(self, p: F64) -> F64:
        p = np.ascontiguousarray(p, dtype=np.float64)
        if self.period is None or len(p) == 0:
            return p
        out = np.empty_like(p)
        last = math.nan if self._last is None else self._last
        self.turns = _kernels.unwrap(p, self.period, self.turns, last, out)
        if math.isfinite(float(p[-1])):
            self._last = float(p[-1])
        return out


# ------------------------------------------------------------------------- equation
class Equation:
    """One regression equation of a model: its target, columns and parameters."""

    def __init__(self, model: Model, name: str, effects: tuple[Effect, ...]) -> None:
        self.model = model
        #: ``"mechanical"`` or ``"electrical"``.
        self.name = name
        #: MECHANICAL (0) or ELECTRICAL (1), the DBC ``Equation`` bit.
        self.index = EquationId.from_label(name)
        self.effects = effects
        axis = model.axis
        if name == ELECTRICAL:
            self.target = TargetSpec(name, "q-axis voltage u", "V", "voltage", 1.0)
        elif model.target == "torque":
            what = ("motor torque T reported by the drive" if axis == "rotary" else
                    "motor force F reported by the drive")
            self.target = TargetSpec(name, what, target_unit(name, axis, True), "torque", 1.0)
        elif model.kt is None:
            self.target = TargetSpec(name, "q-axis current i (Kt unknown)", "A", "current", 1.0)
        else:
            what = "motor torque Kt*i" if axis == "rotary" else "motor force Kf*i"
            self.target = TargetSpec(name, what, target_unit(name, axis, True), "current",
                                     model.kt)
        cols: list[Column] = []
        params: list[ParameterSpec] = []
        for e in effects:
            cols.extend(e.columns())
            params.extend(e.parameters(kt_known=model.torque_known or name == ELECTRICAL))
        self.columns: tuple[Column, ...] = tuple(cols)
        self.parameters: tuple[ParameterSpec, ...] = tuple(params)
        self.n = len(self.columns)
        req = {self.target.signal}
        for e in effects:
            req |= e.requires
        #: Signal roles this equation reads.
        self.requires: frozenset[str] = frozenset(req)
        self.needs_position = "position" in self.requires
        self.scaling = self._scaling()
        self._factors = self.scaling.factors

    def __repr__(self) -> str:
        return (f"Equation({self.name!r}, target={self.target.description!r}, "
                f"parameters={[p.name for p in self.parameters]})")

    @property
    def holds(self) -> tuple[str, ...]:
        """SVF hold of the target and of every column: ``"zoh"`` when it reads a held signal."""
        held = self.model.held
        out = ["zoh" if self.target.signal in held else "foh"]
        out += ["zoh" if c.reads & held else "foh" for c in self.columns]
        return tuple(out)

    @property
    def intrinsic(self) -> tuple[bool, ...]:
        """Which columns are bounded by their own function (``tanh``, ``sin``, a constant,
        a user term with a configured range) rather than by the signals: their bound is
        the same with every signal range doubled, and no value can exceed it."""
        r = self.model.ranges
        doubled = {k: (2.0 * lo, 2.0 * hi) for k, (lo, hi) in r.items()}
        return tuple(not col.derivative
                     and tuple(map(float, col.range(r))) == tuple(map(float, col.range(doubled)))
                     for col in self.columns)

    @property
    def derivative_mask(self) -> tuple[bool, ...]:
        """Which columns go through ``sF`` (True) rather than ``F``."""
        return tuple(c.derivative for c in self.columns)

    def _scaling(self) -> Scaling:
        m = self.model
        f_gain, sf_gain = gain_bounds(m.cutoff_hz, m.zeta)
        r = m.ranges
        lo, hi = r[self.target.signal]
        g = self.target.gain
        ty = self._filtered_bound(g * lo, g * hi, False, f_gain, sf_gain)
        bounds = []
        for col, p in zip(self.columns, self.parameters, strict=True):
            clo, chi = col.range(r)
            b = self._filtered_bound(clo, chi, col.derivative, f_gain, sf_gain)
            if col.derivative and col.rate is not None and col.rate in r:
                # sF[w] = F[dw/dt]: a configured derivative range bounds it too
                b = min(b, self._filtered_bound(*r[col.rate], False, f_gain, sf_gain))
            if not math.isfinite(b):
                raise ConfigError(
                    f"{m.source}: column {p.name} has no finite range "
                    f"({clo!r}, {chi!r}) for normalisation; give the term a range = [lo, hi]"
                    f" or set the ranges of the signals it reads in [model.ranges]")
            bounds.append(b)
        # exponents given (frozen by a calibration, canrls.processor, or configured) win
        # over those of the bounds, column by column: {"target": s_y, parameter: s_j}
        given = m.exponents.get(self.name, {})
        return Scaling(
            columns=tuple(given.get(p.name, _exponent(b))
                          for p, b in zip(self.parameters, bounds, strict=True)),
            target=given.get("target", _exponent(ty)),
            column_bounds=tuple(bounds), target_bound=ty)

    @staticmethod
    def _filtered_bound(lo: float, hi: float, derivative: bool, f_gain: float,
                        sf_gain: float) -> float:
        lo, hi = min(lo, hi), max(lo, hi)
        half = 0.5 * (hi - lo)
        if derivative:
            return sf_gain * half
        return abs(0.5 * (lo + hi)) + f_gain * half

    def builder(self, dt: float) -> RegressorBuilder:
        """A fresh stateful regressor builder for sample period ``dt`` [s]."""
        return RegressorBuilder(self, dt)

    def to_physical(self, theta_norm: npt.ArrayLike) -> F64:
        """Physical parameters from normalised ones: ``theta_j * 2**(s_y - s_j)``.

        Works on ``(n,)`` and on ``(..., n)`` traces; exact (powers of two).
        """
        th = np.asarray(theta_norm, dtype=np.float64)
        return th * self._factors  # type: ignore[no-any-return]

    def sigma_to_physical(self, std_norm: npt.ArrayLike) -> F64:
        """Standard deviations of the parameters in physical units (same factors)."""
        return self.to_physical(std_norm)

    def to_normalised(self, theta_phys: npt.ArrayLike) -> F64:
        """Inverse of :meth:`to_physical` (e.g. to start an estimator from known values)."""
        th = np.asarray(theta_phys, dtype=np.float64)
        return th / self._factors  # type: ignore[no-any-return]

    def target_to_physical(self, y_norm: npt.ArrayLike) -> F64:
        """A normalised target or residual in the target unit: ``y * 2**s_y``."""
        s = self.scaling.target
        if -1074 <= s <= 1023:
            # multiplying by the exact power of two rounds once, as ldexp does (and faster)
            return np.asarray(y_norm, dtype=np.float64) * math.ldexp(1.0, s)
        return np.ldexp(np.asarray(y_norm, dtype=np.float64), s)


class RegressorBuilder:
    """Stateful: turns :class:`~canrls.signals.Signals` blocks into :class:`RegressorBlock`\\ s.

    ``process`` may be called with blocks of any size (including empty); the SVF state
    and the position turn count are carried, so the concatenated output is bit-identical
    to processing everything at once. ``reset`` restarts the filter and the unwrapping.

    A value that is not finite (a user term outside its domain, ``1/speed`` at rest)
    would stay in the filter's state for good. Such a value is replaced by the last
    finite value of its column before it enters the filter, and the row is marked in
    ``nonfinite``: the stand-in value stays in the filter's output for a while, so
    the pipeline leaves out that row and the filter's warm-up after it, as after a gap.
    """

    def __init__(self, equation: Equation, dt: float) -> None:
        m = equation.model
        self.equation = equation
        try:
            self.svf = SVF(m.cutoff_hz, dt, m.zeta, equation.holds)
        except ConfigError as e:
            raise ConfigError(f"{m.source}: model.filter.cutoff_hz = {m.cutoff_hz!r} with "
                              f"dt = {dt!r}: {e}") from e
        self.dt = self.svf.dt
        period = 2.0 * math.pi if m.axis == "rotary" else m.wrap
        self.unwrapper = PositionUnwrapper(period)
        self._deriv_idx = np.flatnonzero([False, *equation.derivative_mask])
        self._neg_exp = -np.array([equation.scaling.target, *equation.scaling.columns],
                                  dtype=np.int64)
        # the same normalisation as factors: x * 2**-s is x scaled exactly as ldexp does
        # (one rounding of the exact product), as long as 2**-s is a double
        self._deriv = np.array([False, *equation.derivative_mask], dtype=np.bool_)
        self._scale: F64 | None = None
        if np.all((self._neg_exp >= -1074) & (self._neg_exp <= 1023)):
            self._scale = np.ldexp(np.ones(len(self._neg_exp)), self._neg_exp)
        self._raw = np.empty((0, equation.n + 1))
        self._last_finite = np.zeros(equation.n + 1)

    @property
    def n(self) -> int:
        return self.equation.n

    def rescale(self, equation: Equation) -> None:
        """Normalise from now on with ``equation``'s exponents (the same columns); the
        filter's state, which holds unnormalised values, carries on."""
        self.equation = equation
        self.normalise_as(equation.scaling)

    def normalise_as(self, scaling: Scaling) -> None:
        """Normalise from now on with ``scaling``'s exponents (of the same columns)."""
        self._neg_exp = -np.array([scaling.target, *scaling.columns], dtype=np.int64)
        self._scale = None
        if np.all((self._neg_exp >= -1074) & (self._neg_exp <= 1023)):
            self._scale = np.ldexp(np.ones(len(self._neg_exp)), self._neg_exp)

    def reset(self) -> None:
        self.svf.reset()
        self.unwrapper.reset()
        self._last_finite = np.zeros(self.equation.n + 1)

    def _replace_nonfinite(self, raw: F64) -> npt.NDArray[np.bool_] | None:
        """Replace each non-finite value of ``raw`` by the last finite value of its column
        (carried between blocks; 0 before any); the rows that had one, or ``None``."""
        n = len(raw)
        if n == 0:
            return None
        if math.isfinite(raw.sum()):  # a NaN or an infinity makes the sum one too
            np.copyto(self._last_finite, raw[-1])
            return None
        finite = np.isfinite(raw)
        if finite.all():  # only the sum overflowed
            np.copyto(self._last_finite, raw[-1])
            return None
        rows = np.arange(n)
        for j in np.flatnonzero(~finite.all(axis=0)):
            # the row of the last finite value at or before each row (-1: none in this block)
            at = np.maximum.accumulate(np.where(finite[:, j], rows, -1))
            raw[:, j] = np.where(at >= 0, raw[np.maximum(at, 0), j], self._last_finite[j])
        self._last_finite = raw[-1].copy()
        return ~finite.all(axis=1)

    def _frame(self, signals: Any) -> Frame:
        eq = self.equation
        for role in eq.requires:
            if getattr(signals, role, None) is None:
                users = [e.name for e in eq.effects if role in e.requires] or ["target"]
                raise SignalError(
                    f"{eq.model.source}: the {eq.name} equation needs signal {role!r} "
                    f"(for {', '.join(users)}), which this block does not carry")

        def arr(v: Any) -> F64 | None:
            return None if v is None else np.ascontiguousarray(v, dtype=np.float64)

        pos = arr(getattr(signals, "position", None))
        angle = None
        if pos is not None and eq.needs_position:
            raw = pos
            pos = self.unwrapper.process(raw)
            m = eq.model
            angle = raw if m.axis == "rotary" else Frame.phase(pos, m.axis, m.pitch)
        return Frame(t=arr(signals.t), current=arr(getattr(signals, "current", None)),
                     speed=arr(signals.speed), position=pos,  # type: ignore[arg-type]
                     voltage=arr(getattr(signals, "voltage", None)), angle=angle,
                     torque=arr(getattr(signals, "torque", None)))

    def noise_covariance(self, signals: Any, noise: Mapping[str, float],
                         rows: npt.NDArray[np.bool_] | None = None) -> F64:
        r"""Covariance of the noise each filtered column carries per row, from white
        noise of standard deviation ``noise[role]`` on each measured signal, linearised on
        ``signals`` (the calibration window), in unnormalised units:

        .. math::

            E[n_j n_k] = \sum_s \sigma_s^2\,\overline{g_{js} g_{ks}}
                         \sum_m h_j[m]\,h_k[m], \qquad g_{js} = \partial c_j/\partial s

        with ``h_j`` the impulse response of the column's filter (``F`` or ``sF``, its
        hold) and the slope ``g`` taken over ``±sigma`` (a column that saturates, like a
        ``tanh`` away from zero speed, passes little noise), averaged over ``rows`` (the
        rows the estimator would use: within its speed limits). With fewer than
        :data:`MIN_NOISE_ROWS` of those, only columns whose slope is the same on every
        row (linear in the signal) are counted. It does not touch the builder's state.
        """
        eq = self.equation
        frame = RegressorBuilder(eq, self.dt)._frame(signals)
        N, n = len(frame.t), eq.n
        cov = np.zeros((n, n))
        if N == 0:
            return cov
        m = eq.model
        holds = eq.holds[1:]
        h = {(hold, d): impulse_response(m.cutoff_hz, self.dt, m.zeta, hold)[int(d)]  # type: ignore[arg-type]
             for hold, d in {(hd, c.derivative) for hd, c in zip(holds, eq.columns, strict=True)}}
        H = np.array([[float(h[holds[j], eq.columns[j].derivative]
                             @ h[holds[k], eq.columns[k].derivative]) for k in range(n)]
                      for j in range(n)])
        for role, sigma in noise.items():
            if not (sigma > 0 and math.isfinite(sigma)) or getattr(frame, role, None) is None:
                continue
            g = np.zeros((N, n))
            for j, col in enumerate(eq.columns):
                if role in col.reads:
                    up, down = _nudged(frame, role, sigma, m), _nudged(frame, role, -sigma, m)
                    g[:, j] = (col.raw(up) - col.raw(down)) / (2.0 * sigma)
            g[~np.isfinite(g)] = 0.0
            if rows is not None and np.count_nonzero(rows) >= MIN_NOISE_ROWS:
                g = g[rows]
            else:
                # the operating point is unknown: linear columns only
                g[:, np.ptp(g, axis=0) > 1e-9 * np.max(np.abs(g), axis=0)] = 0.0
            # E[n_j n_k] = sigma^2 mean(g_j g_k) sum_m h_j h_k
            cov += sigma * sigma * (g.T @ g / len(g)) * H
        return cov

    def process(self, signals: Any) -> RegressorBlock:
        """Regressors of one block (see the module docstring)."""
        phi, y, t, nonfinite = self.regressors(signals)
        return RegressorBlock(phi=phi, y=y, t=t, nonfinite=nonfinite)

    def regressors(self, signals: Any
                    ) -> tuple[F64, F64, F64, npt.NDArray[np.bool_] | None]:
        """``(phi, y, t, nonfinite)`` of :meth:`process`, without the result object."""
        eq = self.equation
        frame = self._frame(signals)
        n = len(frame.t)
        # unfiltered target and columns, in a buffer kept between blocks (it never leaves
        # here; a fresh one per block would cost page faults)
        if self._raw.shape[0] < n:
            self._raw = np.empty((max(n, (self._raw.shape[0] * 3) // 2), eq.n + 1))
        raw = self._raw[:n]
        tgt = frame.get(eq.target.signal)
        # target: Kt * i (torque), i, the reported torque T, or u
        if eq.target.gain != 1.0:
            np.multiply(tgt, eq.target.gain, out=raw[:, 0])
        else:
            raw[:, 0] = tgt
        for j, col in enumerate(eq.columns):
            raw[:, j + 1] = col.raw(frame)
        nonfinite = self._replace_nonfinite(raw)
        if self._scale is not None:
            # filter, pick F or sF and normalise in one pass (same values as below)
            y = np.empty(n)
            phi = np.empty((n, eq.n))
            self.svf.process_scaled(raw, self._deriv, self._scale, y, phi)
            return phi, y, frame.t, nonfinite
        f, sf = self.svf.process(raw)
        # value columns and target through F, derivative columns through sF
        if self._deriv_idx.size:
            f[:, self._deriv_idx] = sf[:, self._deriv_idx]
        # exact power-of-two normalisation
        np.ldexp(f, self._neg_exp, out=f)
        return np.ascontiguousarray(f[:, 1:]), f[:, 0].copy(), frame.t, nonfinite


#: Fewest rows within the speed limits on which :meth:`RegressorBuilder.noise_covariance`
#: takes the slopes of columns that are not linear in a signal.
MIN_NOISE_ROWS = 16


def _nudged(frame: Frame, role: str, by: float, model: Model) -> Frame:
    """``frame`` with signal ``role`` moved by ``by`` (the position's angle with it)."""
    v = getattr(frame, role) + by
    if role != "position":
        return dataclasses.replace(frame, **{role: v})
    angle = v if model.axis == "rotary" else Frame.phase(v, model.axis, model.pitch)
    return dataclasses.replace(frame, position=v, angle=angle)


# ---------------------------------------------------------------------------- model
class Model:
    """Effects, target and filter settings; validated once when built.

    :param effects: effect names (``"inertia"``, ``"cogging:24"``, ``"user:NAME"``) or
        :class:`~canrls.estimation.effects.Effect` objects, in column order.
    :param axis: ``"rotary"`` or ``"linear"``.
    :param kt: torque (force) constant; ``None``: the mechanical target is the current.
    :param target: the mechanical target, ``"current"`` (``Kt*i``, or ``i`` without
        ``kt``) or ``"torque"`` (the torque the drive reports, N·m; linear axis: force,
        N; no ``kt``).
    :param pitch: linear axis: metres per period of the periodic terms.
    :param wrap: linear axis: wrap period of the measured position, or ``None``.
    :param cutoff_hz, zeta: SVF settings (:class:`canrls.estimation.svf.SVF`).
    :param held: signal roles held constant over each sample period (zero-order hold);
        default ``("voltage",)``.
    :param coulomb_band: smoothing band of ``sgn_e``; :param stribeck_speed: ``ws``.
    :param terms: user terms, ``{NAME: {"expr", "unit", "equation", "range"}}`` or a list of
        tables with a ``name`` key (as ``[[model.terms]]``).
    :param ranges: ``{role: (lo, hi)}`` for ``current``, ``speed``, ``voltage``
        (``position`` optional), merged over the defaults.
    :param available_signals: signal roles the drive sends (``position``, ``voltage``,
        ``torque``; ``current`` and ``speed`` are always there, except that a drive
        sending ``torque`` has ``current`` only when it says so); ``None``: all.
    :param source: where the configuration came from, for error messages.
    :raises ConfigError: an invalid setting; :class:`EffectError` for effects.
    """

    def __init__(self, effects: Iterable[str | Effect] = (), *, axis: str = "rotary",
                 kt: float | None = None, target: str = "current",
                 pitch: float = DEFAULT_PITCH,
                 wrap: float | None = None, cutoff_hz: float = DEFAULT_CUTOFF_HZ,
                 zeta: float = DEFAULT_ZETA, held: Iterable[str] = ("voltage",),
                 coulomb_band: float = DEFAULT_BAND,
                 stribeck_speed: float = DEFAULT_STRIBECK_SPEED,
                 terms: Mapping[str, Mapping[str, Any]] | Sequence[Mapping[str, Any]]
                 | None = None,
                 ranges: Mapping[str, Sequence[float]] | None = None,
                 available_signals: Iterable[str] | None = None,
                 source: str = "<model>",
                 ranges_given: Iterable[str] | None = None,
                 scaling: Mapping[str, Mapping[str, int]] | None = None,
                 options_given: Iterable[str] | None = None) -> None:
        self.source = source
        #: Which of :data:`DATA_OPTIONS` were given (configured, or frozen by a
        #: calibration); the front end scales the others from the data
        #: (:func:`canrls.processor.data_defaults`). Default: all given.
        self.options_given: frozenset[str] = frozenset(
            DATA_OPTIONS if options_given is None else options_given) & frozenset(DATA_OPTIONS)
        if axis not in ("rotary", "linear"):
            raise ConfigError(_fmt(source, "model.axis", axis, "must be 'rotary' or 'linear'"))
        self.axis: Axis = axis  # type: ignore[assignment]
        self.kt = None if kt is None else _number(source, "model.kt", kt, nonzero=True)
        if target not in TARGETS:
            raise ConfigError(_fmt(source, "model.target", target,
                                   f"must be one of {', '.join(map(repr, TARGETS))}"))
        #: The mechanical target: ``"current"`` or ``"torque"`` (reported by the drive).
        self.target: str = target
        if target == "torque" and self.kt is not None:
            raise ConfigError(_fmt(source, "model.kt", kt,
                                   "the mechanical target is the torque the drive reports "
                                   "(parameters in N·m, or N on a linear axis): Kt is not "
                                   "used; leave it out (or set model.target = \"current\" to "
                                   "identify on the current)"))
        self.pitch = _number(source, "model.pitch", pitch, positive=True)
        self.wrap = None if wrap is None else _number(source, "model.wrap", wrap, positive=True)
        if self.wrap is not None and self.axis == "rotary":
            raise ConfigError(_fmt(source, "model.wrap", wrap,
                                   "only for a linear axis (rotary positions wrap at 2 pi)"))
        self.cutoff_hz = _number(source, "model.filter.cutoff_hz", cutoff_hz, positive=True)
        self.zeta = _number(source, "model.filter.zeta", zeta, positive=True)
        if not ZETA_RANGE[0] <= self.zeta <= ZETA_RANGE[1]:
            raise ConfigError(_fmt(source, "model.filter.zeta", zeta,
                                   f"the damping ratio must be in [{ZETA_RANGE[0]:g}, "
                                   f"{ZETA_RANGE[1]:g}]"))
        if isinstance(held, str) or not isinstance(held, Iterable):
            raise ConfigError(_fmt(source, "model.filter.held", held,
                                   f"must be a list of signals ({', '.join(_HELD_ROLES)})"))
        held = tuple(held)
        for h in held:
            if h not in _HELD_ROLES:
                raise ConfigError(_fmt(source, "model.filter.held", list(held),
                                       f"unknown signal {h!r} (valid: "
                                       f"{', '.join(_HELD_ROLES)})"))
        #: Signal roles held over each sample period (filtered with a zero-order hold).
        self.held: frozenset[str] = frozenset(held)
        self.coulomb_band = _number(source, "model.coulomb.band", coulomb_band, positive=True)
        self.stribeck_speed = _number(source, "model.stribeck.speed", stribeck_speed,
                                      positive=True)
        self.terms = self._check_terms(terms)
        self.ranges = self._check_ranges(ranges)
        self.exponents = self._check_exponents(scaling)
        #: Signal roles whose range was given (configured, or frozen by a calibration);
        #: the others hold defaults that the front end replaces by measured ones.
        self.ranges_given: frozenset[str] = frozenset(
            (ranges or {}) if ranges_given is None else ranges_given) & frozenset(self.ranges)
        if available_signals is None:
            self.available_signals: frozenset[str] | None = None
        else:
            av = frozenset(available_signals)
            bad = sorted(av - {"t", "current", "speed", "position", "voltage", "torque"})
            if bad:
                raise ConfigError(_fmt(source, "available_signals", sorted(av),
                                       f"unknown role(s) {bad}"))
            # a drive reporting its torque sends the current only when it says so
            self.available_signals = av | (_ALWAYS - {"current"} if "torque" in av
                                           else _ALWAYS)
            if target == "torque" and "torque" not in av:
                raise ConfigError(_fmt(source, "model.target", target,
                                       "the drive sends no torque signal (map one: "
                                       "torque=MESSAGE.SIGNAL)"))
        self.effects: tuple[Effect, ...] = self._build_effects(effects)
        self.equations: tuple[Equation, ...] = self._build_equations()
        av = self.available_signals
        for eq in self.equations:
            if av is not None and eq.name == MECHANICAL and eq.target.signal not in av:
                raise ConfigError(_fmt(source, "model.target", self.target,
                                       f"the drive sends no {eq.target.signal} signal "
                                       f"(it sends {', '.join(sorted(av - {'t'}))})"))

    # -- validation -------------------------------------------------------------------
    @property
    def torque_known(self) -> bool:
        """True when the mechanical target is a torque (``Kt*i`` or the drive's own):
        parameters in N·m (N), not per ampere."""
        return self.kt is not None or self.target == "torque"

    @property
    def effect_options(self) -> dict[str, Any]:
        """The shared options :func:`canrls.estimation.effects.parse_effect` builds effects with."""
        return {"axis": self.axis, "pitch": self.pitch, "band": self.coulomb_band,
                "speed": self.stribeck_speed, "terms": self.terms}

    def _check_terms(self, terms: Any) -> dict[str, dict[str, Any]]:
        src = self.source
        if terms is None:
            return {}
        out: dict[str, dict[str, Any]] = {}
        if isinstance(terms, Mapping):
            items = [(str(k), v, f"model.terms.{k}") for k, v in terms.items()]
        elif isinstance(terms, Sequence) and not isinstance(terms, str):
            items = []
            for i, t in enumerate(terms):
                key = f"model.terms[{i}]"
                if not isinstance(t, Mapping) or "name" not in t:
                    raise ConfigError(_fmt(src, key, t, "must be a table with a 'name'"))
                items.append((t["name"], {k: v for k, v in t.items() if k != "name"}, key))
        else:
            raise ConfigError(_fmt(src, "model.terms", terms, "must be a list of tables"))
        for name, t, key in items:
            if not isinstance(t, Mapping):
                raise ConfigError(_fmt(src, key, t, "must be a table"))
            if not isinstance(name, str) or not name.isidentifier():
                raise ConfigError(_fmt(src, f"{key}.name", name, "must be an identifier"))
            if name in out:
                raise ConfigError(_fmt(src, f"{key}.name", name, "duplicate term name"))
            same = [n for n in out if n.upper() == name.upper()]
            if same:  # the generated C names parameters in capitals: they would collide
                raise ConfigError(_fmt(src, f"{key}.name", name,
                                       f"differs from term {same[0]!r} only in case"))
            bad = sorted(set(t) - {"expr", "unit", "equation", "range"})
            if bad:
                raise ConfigError(_fmt(src, f"{key}.{bad[0]}", t[bad[0]],
                                       "unknown key (valid: name, expr, unit, equation, "
                                       "range)"))
            if not isinstance(t.get("expr"), str):
                raise ConfigError(_fmt(src, f"{key}.expr", t.get("expr"),
                                       "required, a string expression"))
            try:  # compile now so that a bad term fails at load time, even if unused
                UserTerm(name, axis=self.axis, pitch=self.pitch,
                         **{k: (tuple(v) if k == "range" and isinstance(v, list) else v)
                            for k, v in t.items()})
            except ConfigError as e:
                raise type(e)(f"{src}: {key} ({name}): {e}") from e
            out[name] = dict(t)
        return out

    def _check_exponents(self, scaling: Any) -> dict[str, dict[str, int]]:
        if scaling is None:
            return {}
        if not isinstance(scaling, Mapping):
            raise ConfigError(_fmt(self.source, "model.scaling", scaling, "must be a table"))
        out = {}
        for k, v in scaling.items():
            key = f"model.scaling.{k}"
            if k not in ("mechanical", ELECTRICAL):
                raise ConfigError(_fmt(self.source, key, v, "unknown equation (valid: "
                                                            f"mechanical, {ELECTRICAL})"))
            if not isinstance(v, Mapping):
                raise ConfigError(_fmt(self.source, key, v, 'must be a table of exponents '
                                                            '{"target" = s_y, PARAMETER = s}'))
            for name, s in v.items():
                if isinstance(s, bool) or not isinstance(s, int) or not -1000 <= s <= 1000:
                    raise ConfigError(_fmt(self.source, f"{key}.{name}", s,
                                           "must be an integer exponent in [-1000, 1000]"))
            out[k] = {str(name): int(s) for name, s in v.items()}
        return out

    def _check_ranges(self, ranges: Any) -> dict[str, Range]:
        src = self.source
        out: dict[str, Range] = dict(DEFAULT_RANGES)
        if self.axis == "linear":
            out["speed"] = _LINEAR_SPEED
        if ranges is None:
            return out
        if not isinstance(ranges, Mapping):
            raise ConfigError(_fmt(src, "model.ranges", ranges, "must be a table"))
        for k, v in ranges.items():
            key = f"model.ranges.{k}"
            if k not in _RANGE_KEYS:
                raise ConfigError(_fmt(src, key, v, f"unknown signal (valid: "
                                                    f"{', '.join(_RANGE_KEYS)})"))
            if (not isinstance(v, Sequence) or isinstance(v, str) or len(v) != 2):
                raise ConfigError(_fmt(src, key, v, "must be [lo, hi]"))
            lo = _number(src, key, v[0])
            hi = _number(src, key, v[1])
            if not lo < hi:
                raise ConfigError(_fmt(src, key, v, "must be [lo, hi] with lo < hi"))
            out[k] = (lo, hi)
        return out

    def _build_effects(self, effects: Iterable[str | Effect]) -> tuple[Effect, ...]:
        src = self.source
        if isinstance(effects, str):
            raise ConfigError(_fmt(src, "model.effects", effects, "must be a list of names"))
        out: list[Effect] = []
        seen: set[str] = set()
        for i, spec in enumerate(effects):
            key = f"model.effects[{i}]"
            if isinstance(spec, Effect):
                eff = spec
                if eff.axis != self.axis:
                    raise EffectError(_fmt(src, key, eff.name,
                                           f"effect built for the {eff.axis} axis, "
                                           f"the model is {self.axis}"))
                try:
                    same = parse_effect(eff.name, self.effect_options) == eff
                except ConfigError:
                    same = False
                if not same:
                    raise EffectError(_fmt(src, key, eff, "its options differ from the "
                                           "model's; set pitch, band, speed and terms on the "
                                           "model (one source of truth)"))
            elif isinstance(spec, str):
                try:
                    eff = parse_effect(spec, self.effect_options)
                except EffectError as e:
                    raise EffectError(_fmt(src, key, spec, str(e))) from e
                except ConfigError as e:  # an expression error in a user term
                    raise type(e)(_fmt(src, key, spec, str(e))) from e
            else:
                raise EffectError(_fmt(src, key, spec, "must be an effect name"))
            if eff.name in seen:
                raise EffectError(_fmt(src, key, spec, f"duplicate effect {eff.name!r}"))
            seen.add(eff.name)
            if self.available_signals is not None:
                missing = sorted(eff.requires - self.available_signals)
                if missing:
                    raise EffectError(_fmt(src, key, eff.name,
                                           f"needs signal(s) {missing}, which the drive "
                                           f"does not send (available: "
                                           f"{sorted(self.available_signals)})"))
            out.append(eff)
        if not out:
            raise ConfigError(_fmt(src, "model.effects", [], "no effects: give at least one"))
        names = {e.name for e in out}
        if "electrical" not in names:
            for i, e in enumerate(out):
                if e.equation == ELECTRICAL:
                    raise EffectError(_fmt(src, f"model.effects[{i}]", e.name,
                                           "belongs to the electrical equation; add "
                                           "'electrical' to the effects"))
        return tuple(out)

    def _build_equations(self) -> tuple[Equation, ...]:
        eqs = []
        mech = tuple(e for e in self.effects if e.equation == MECHANICAL)
        elec = tuple(e for e in self.effects if e.equation == ELECTRICAL)
        if mech:
            eqs.append(Equation(self, MECHANICAL, mech))
        if elec:
            eqs.append(Equation(self, ELECTRICAL, elec))
        return tuple(eqs)

    # -- views ------------------------------------------------------------------------
    def __repr__(self) -> str:
        target = "" if self.target == "current" else f", target={self.target!r}"
        return (f"Model(effects={[e.name for e in self.effects]}, axis={self.axis!r}, "
                f"kt={self.kt!r}{target}, source={self.source!r})")

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Model) and other.to_dict() == self.to_dict()

    __hash__ = None  # type: ignore[assignment]

    @property
    def held_list(self) -> list[str]:
        """:attr:`held` in a fixed order (as the configuration writes it)."""
        return [r for r in _HELD_ROLES if r in self.held]

    @property
    def effect_names(self) -> tuple[str, ...]:
        return tuple(e.name for e in self.effects)

    @property
    def parameters(self) -> tuple[ParameterSpec, ...]:
        """All parameters, equation by equation (mechanical first)."""
        return tuple(p for eq in self.equations for p in eq.parameters)

    @property
    def active_effects(self) -> int:
        """Bit ``EffectId - 1`` set for every effect kind present (DBC ``ActiveEffects``)."""
        bits = 0
        for e in self.effects:
            bits |= 1 << (e.effect_id - 1)
        return bits

    def equation(self, name: str) -> Equation:
        """The equation called ``name`` (``"mechanical"`` or ``"electrical"``)."""
        for eq in self.equations:
            if eq.name == name:
                return eq
        raise KeyError(f"model has no {name!r} equation (has: "
                       f"{[e.name for e in self.equations]})")

    # -- derivation -------------------------------------------------------------------
    def _kwargs(self) -> dict[str, Any]:
        return dict(axis=self.axis, kt=self.kt, target=self.target, pitch=self.pitch,
                    wrap=self.wrap,
                    cutoff_hz=self.cutoff_hz, zeta=self.zeta, held=self.held_list,
                    coulomb_band=self.coulomb_band, stribeck_speed=self.stribeck_speed,
                    terms=self.terms, ranges=self.ranges,
                    available_signals=self.available_signals, source=self.source,
                    ranges_given=self.ranges_given, scaling=self.exponents,
                    options_given=self.options_given)

    def with_options(self, **values: float) -> Model:
        """A new model with some of :data:`DATA_OPTIONS` set (``coulomb_band=0.04``);
        those count as given from then on. The effects are rebuilt with them."""
        bad = sorted(set(values) - set(DATA_OPTIONS))
        if bad:
            raise ConfigError(f"{self.source}: with_options: unknown option(s) {bad} "
                              f"(valid: {', '.join(DATA_OPTIONS)})")
        kw = self._kwargs()
        kw.update(values)
        kw["options_given"] = self.options_given | frozenset(values)
        return Model([e.name for e in self.effects], **kw)

    def with_cutoff(self, cutoff_hz: float) -> Model:
        """The same model with the state-variable filter's cutoff at ``cutoff_hz``."""
        kw = self._kwargs()
        kw["cutoff_hz"] = cutoff_hz
        return Model(self.effects, **kw)

    def with_scaling(self, exponents: Mapping[str, Mapping[str, int]]) -> Model:
        """A new model whose equations use the given power-of-two exponents,
        ``{equation: {"target": s_y, parameter name: s_j}}`` (:attr:`Equation.scaling`),
        instead of the ones its ranges give; a column not named keeps its bound's."""
        kw = self._kwargs()
        kw["scaling"] = exponents
        return Model(self.effects, **kw)

    def with_ranges(self, measured: Mapping[str, Sequence[float]]) -> Model:
        """A new model whose signal ranges not given (:attr:`ranges_given`) are
        ``measured``; every range of the new model counts as given (it is frozen)."""
        ranges = {k: (tuple(measured[k]) if k in measured and k not in self.ranges_given
                      else v) for k, v in self.ranges.items()}
        ranges.update({k: tuple(v) for k, v in measured.items()
                       if k not in ranges and k in _RANGE_KEYS})
        kw = self._kwargs()
        kw.update(ranges=ranges, ranges_given=frozenset(ranges))
        return Model(self.effects, **kw)

    def with_effects(self, add: Iterable[str | Effect] = (),
                     remove: Iterable[str] = ()) -> Model:
        """A new model with effects removed and added (appended, in order); validated.

        :raises EffectError: removing an effect the model does not have, adding one it
            already has, or any error building the new effects.
        """
        current = list(self.effects)
        for name in remove:
            key = _canonical(name)
            idx = [i for i, e in enumerate(current) if e.name == key]
            if not idx:
                raise EffectError(f"{self.source}: cannot remove effect {name!r}: not in the "
                                  f"model (effects: {', '.join(e.name for e in current)})")
            del current[idx[0]]
        names = {e.name for e in current}
        new: list[str | Effect] = list(current)
        for spec in add:
            eff = spec if isinstance(spec, Effect) else parse_effect(spec, self.effect_options)
            if eff.name in names:
                raise EffectError(f"{self.source}: cannot add effect {eff.name!r}: already in "
                                  f"the model")
            names.add(eff.name)
            new.append(eff)
        return Model(new, **self._kwargs())

    # -- configuration ----------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """The ``[model]`` table that rebuilds this model (``Model.from_dict``)."""
        d: dict[str, Any] = {"axis": self.axis, "pitch": self.pitch}
        if self.wrap is not None:
            d["wrap"] = self.wrap
        if self.kt is not None:
            d["kt"] = self.kt
        if self.target != "current":
            d["target"] = self.target
        d["effects"] = [e.name for e in self.effects]
        d["filter"] = {"cutoff_hz": self.cutoff_hz, "zeta": self.zeta, "held": self.held_list}
        d["coulomb"] = {"band": self.coulomb_band}
        d["stribeck"] = {"speed": self.stribeck_speed}
        d["terms"] = [{"name": k, **{kk: (list(vv) if kk == "range" else vv)
                                     for kk, vv in v.items()}} for k, v in self.terms.items()]
        d["ranges"] = {k: [lo, hi] for k, (lo, hi) in self.ranges.items()}
        if self.exponents:
            d["scaling"] = {k: dict(v) for k, v in self.exponents.items()}
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], *, source: str = "<dict>",
                  available_signals: Iterable[str] | None = None) -> Model:
        """Build from the contents of a ``[model]`` table (see the module docstring)."""
        if not isinstance(d, Mapping):
            raise ConfigError(_fmt(source, "model", d, "must be a table"))
        for k in d:
            if k not in _MODEL_KEYS:
                raise ConfigError(_fmt(source, f"model.{k}", d[k],
                                       f"unknown key (valid: {', '.join(_MODEL_KEYS)})"))
        kw: dict[str, Any] = {}
        for k in ("axis", "pitch", "wrap", "kt", "target"):
            if k in d:
                kw[k] = d[k]
        for sub, keys in _SUBKEYS.items():
            if sub not in d:
                continue
            t = d[sub]
            if not isinstance(t, Mapping):
                raise ConfigError(_fmt(source, f"model.{sub}", t, "must be a table"))
            for k, v in t.items():
                if k not in keys:
                    raise ConfigError(_fmt(source, f"model.{sub}.{k}", v,
                                           f"unknown key (valid: {', '.join(keys)})"))
            if sub == "filter":
                kw.update({k: t[k] for k in keys if k in t})
            elif sub == "coulomb" and "band" in t:
                kw["coulomb_band"] = t["band"]
            elif sub == "stribeck" and "speed" in t:
                kw["stribeck_speed"] = t["speed"]
        if "effects" in d:
            eff = d["effects"]
            if isinstance(eff, str) or not isinstance(eff, Sequence):
                raise ConfigError(_fmt(source, "model.effects", eff, "must be a list of names"))
            kw["effects"] = list(eff)
        else:
            raise ConfigError(_fmt(source, "model.effects", None, "required"))
        if "terms" in d:
            kw["terms"] = d["terms"]
        if "ranges" in d:
            kw["ranges"] = d["ranges"]
        if "scaling" in d:
            kw["scaling"] = d["scaling"]
        given = {k for k in ("coulomb_band", "stribeck_speed", "pitch") if k in kw}
        return cls(**kw, available_signals=available_signals, source=source,
                   options_given=given)
