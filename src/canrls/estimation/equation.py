"""An equation of the model (:class:`Equation`): its output, parameters and scaling,
and the :class:`RegressorBuilder` that filters and normalises its regressors block by
block (docs/effects.md: "Regressors", "Normalisation" and the filter's holds)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from canrls import _kernels
from canrls.core.effect_names import EquationId
from canrls.core.errors import ConfigError, SignalError
from canrls.estimation.effects import (
    ELECTRICAL,
    Axis,
    Column,
    Effect,
    Frame,
    ParameterSpec,
    output_unit,
)
from canrls.estimation.svf import SVF, Hold, gain_bounds, impulse_response

__all__ = [
    "Equation",
    "OutputSpec",
    "Scaling",
    "RegressorBlock",
    "RegressorBuilder",
    "PositionUnwrapper",
    "MIN_NOISE_ROWS",
]

F64 = npt.NDArray[np.float64]


def _exponent(bound: float) -> int:
    """Smallest s with bound <= 2**s (0 for a zero bound)."""
    if bound <= 0.0:
        return 0
    m, e = math.frexp(bound)  # bound = m * 2**e, 0.5 <= m < 1
    return e - 1 if m == 0.5 else e


# ------------------------------------------------------------------------- results
@dataclass(frozen=True)
class OutputSpec:
    """The left-hand side of an equation: ``gain * signal``."""

    equation: str
    description: str
    unit: str
    signal: str
    gain: float


@dataclass(frozen=True)
class Scaling:
    """Power-of-two normalisation: ``phi_j = F[.] * 2**-columns[j]``, ``y = F[.] * 2**-output``.

    ``column_bounds`` / ``output_bound`` are the worst-case magnitudes of the filtered
    signals the exponents were chosen from.
    """

    columns: tuple[int, ...]
    output: int
    column_bounds: tuple[float, ...]
    output_bound: float

    @property
    def factors(self) -> F64:
        """``2**(s_y - s_j)``: multiply normalised parameters by these."""
        return np.ldexp(np.ones(len(self.columns)),
                        np.array([self.output - s for s in self.columns], dtype=np.int64))


@dataclass(frozen=True)
class RegressorBlock:
    """Normalised regressors of one block: ``y[k] ~ phi[k] @ theta``.

    ``phi`` is ``(N, n)`` float64, ``y`` is ``(N,)`` float64, ``t`` the sample times.
    ``nonfinite`` marks the rows where the output or a column was not finite before
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
class ModelView(Protocol):
    """What an equation reads of the model it belongs to; a
    :class:`~canrls.estimation.model.Model` is one. The model imports its equations, so
    they name what they need of it here rather than import it back."""

    source: str
    axis: Axis
    output: str
    kt: float | None
    pitch: float
    wrap: float | None
    cutoff_hz: float
    zeta: float
    held: frozenset[str]
    coulomb_band: float

    @property
    def ranges(self) -> Mapping[str, tuple[float, float]]: ...

    @property
    def exponents(self) -> Mapping[str, Mapping[str, int]]: ...

    @property
    def torque_known(self) -> bool: ...

    def with_cutoff(self, cutoff_hz: float) -> ModelView:
        """The same model with the filter's cutoff at ``cutoff_hz``."""

    def with_scaling(self, exponents: Mapping[str, Mapping[str, int]]) -> ModelView:
        """The same model with these normalisation exponents."""

    def equation(self, name: str) -> Equation:
        """The model's equation called ``name``."""


class Equation:
    """One regression equation of a model: its output, columns and parameters."""

    def __init__(self, model: ModelView, name: str, effects: tuple[Effect, ...]) -> None:
        self.model = model
        #: ``"mechanical"`` or ``"electrical"``.
        self.name = name
        #: MECHANICAL (0) or ELECTRICAL (1), the DBC ``Equation`` bit.
        self.index = EquationId.from_label(name)
        self.effects = effects
        axis = model.axis
        if name == ELECTRICAL:
            self.output = OutputSpec(name, "q-axis voltage u", "V", "voltage", 1.0)
        elif model.output == "torque":
            what = ("motor torque T reported by the drive" if axis == "rotary" else
                    "motor force F reported by the drive")
            self.output = OutputSpec(name, what, output_unit(name, axis, True), "torque", 1.0)
        elif model.kt is None:
            self.output = OutputSpec(name, "q-axis current i (Kt unknown)", "A", "current", 1.0)
        else:
            what = "motor torque Kt*i" if axis == "rotary" else "motor force Kf*i"
            self.output = OutputSpec(name, what, output_unit(name, axis, True), "current",
                                     model.kt)
        cols: list[Column] = []
        params: list[ParameterSpec] = []
        for e in effects:
            cols.extend(e.columns())
            params.extend(e.parameters(kt_known=model.torque_known or name == ELECTRICAL))
        self.columns: tuple[Column, ...] = tuple(cols)
        self.parameters: tuple[ParameterSpec, ...] = tuple(params)
        self.n = len(self.columns)
        req = {self.output.signal}
        for e in effects:
            req |= e.requires
        #: Signal roles this equation reads.
        self.requires: frozenset[str] = frozenset(req)
        self.needs_position = "position" in self.requires
        self.scaling = self._scaling()
        self._factors = self.scaling.factors

    def __repr__(self) -> str:
        return (f"Equation({self.name!r}, output={self.output.description!r}, "
                f"parameters={[p.name for p in self.parameters]})")

    @property
    def holds(self) -> tuple[Hold, ...]:
        """SVF hold of the output and of every column: ``"zoh"`` when it reads a held signal."""
        held = self.model.held
        out: list[Hold] = ["zoh" if self.output.signal in held else "foh"]
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
        lo, hi = r[self.output.signal]
        g = self.output.gain
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
        # over those of the bounds, column by column: {"output": s_y, parameter: s_j}
        given = m.exponents.get(self.name, {})
        return Scaling(
            columns=tuple(given.get(p.name, _exponent(b))
                          for p, b in zip(self.parameters, bounds, strict=True)),
            output=given.get("output", _exponent(ty)),
            column_bounds=tuple(bounds), output_bound=ty)

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
        return th * self._factors

    def sigma_to_physical(self, std_norm: npt.ArrayLike) -> F64:
        """Standard deviations of the parameters in physical units (same factors)."""
        return self.to_physical(std_norm)

    def to_normalised(self, theta_phys: npt.ArrayLike) -> F64:
        """Inverse of :meth:`to_physical` (e.g. to start an estimator from known values)."""
        th = np.asarray(theta_phys, dtype=np.float64)
        return th / self._factors

    def output_to_physical(self, y_norm: npt.ArrayLike) -> F64:
        """A normalised output or residual in the output unit: ``y * 2**s_y``."""
        s = self.scaling.output
        if -1074 <= s <= 1023:
            # multiplying by the exact power of two rounds once, as ldexp does (and faster)
            return np.asarray(y_norm, dtype=np.float64) * math.ldexp(1.0, s)
        return np.ldexp(np.asarray(y_norm, dtype=np.float64), s)


class RegressorBuilder:
    """Stateful: turns :class:`~canrls.core.samples.Signals` blocks into
    :class:`RegressorBlock`\\ s.

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
        self._neg_exp = -np.array([equation.scaling.output, *equation.scaling.columns],
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
        self._neg_exp = -np.array([scaling.output, *scaling.columns], dtype=np.int64)
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
        with np.errstate(over="ignore", invalid="ignore"):  # huge but finite: below
            total = raw.sum()
        if math.isfinite(total):  # a NaN or an infinity makes the sum one too
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
        return ~np.all(finite, axis=1)

    def _check_finite(self, phi: F64, y: F64, t: F64) -> None:
        """Refuse filtered values beyond a double (finite inputs whose filtered values
        overflow: a ``kt`` of 1e308, a user term of ``exp(700)``), naming the column."""
        if math.isfinite(y.sum()) and math.isfinite(phi.sum()):
            return
        eq = self.equation
        bad_y = ~np.isfinite(y)
        for j, bad in [(-1, bad_y), *enumerate((~np.isfinite(phi)).T)]:
            if not bad.any():
                continue
            at = f"t = {float(t[int(np.argmax(bad))]):.6g} s"
            if j < 0:
                gain = (f"model.kt = {eq.output.gain:g}: " if eq.output.gain != 1.0 else "")
                what = f"the output {eq.output.description} ({eq.output.unit})"
            else:
                gain, what = "", f"the column of {eq.parameters[j].name}"
            raise ConfigError(f"{gain}{what} overflows a double once filtered (from {at}): "
                              f"its values must stay far below 1e308")

    def _frame(self, signals: Any) -> Frame:
        eq = self.equation
        for role in eq.requires:
            if getattr(signals, role, None) is None:
                users = [e.name for e in eq.effects if role in e.requires] or ["output"]
                raise SignalError(
                    f"{eq.model.source}: the {eq.name} equation needs signal {role!r} "
                    f"(for {', '.join(users)}), which this block does not carry")

        def col(v: Any) -> F64:
            return np.ascontiguousarray(v, dtype=np.float64)

        def arr(v: Any) -> F64 | None:
            return None if v is None else col(v)

        pos = arr(getattr(signals, "position", None))
        angle = None
        if pos is not None and eq.needs_position:
            raw = pos
            pos = self.unwrapper.process(raw)
            m = eq.model
            angle = raw if m.axis == "rotary" else Frame.phase(pos, m.axis, m.pitch)
        return Frame(t=col(signals.t), current=arr(getattr(signals, "current", None)),
                     speed=col(signals.speed), position=pos,
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
        h = {(hold, d): impulse_response(m.cutoff_hz, self.dt, m.zeta, hold)[int(d)]
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
        """Regressors of one block (docs/effects.md, *Regressors*)."""
        phi, y, t, nonfinite = self.regressors(signals)
        return RegressorBlock(phi=phi, y=y, t=t, nonfinite=nonfinite)

    def regressors(self, signals: Any
                    ) -> tuple[F64, F64, F64, npt.NDArray[np.bool_] | None]:
        """``(phi, y, t, nonfinite)`` of :meth:`process`, without the result object."""
        eq = self.equation
        frame = self._frame(signals)
        n = len(frame.t)
        # unfiltered output and columns, in a buffer kept between blocks (it never leaves
        # here; a fresh one per block would cost page faults)
        if self._raw.shape[0] < n:
            self._raw = np.empty((max(n, (self._raw.shape[0] * 3) // 2), eq.n + 1))
        raw = self._raw[:n]
        tgt = frame.get(eq.output.signal)
        # output: Kt * i (torque), i, the reported torque T, or u
        if eq.output.gain != 1.0:
            with np.errstate(over="ignore"):  # an overflow is refused below, by name
                np.multiply(tgt, eq.output.gain, out=raw[:, 0])
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
        else:
            f, sf = self.svf.process(raw)
            # value columns and output through F, derivative columns through sF
            if self._deriv_idx.size:
                f[:, self._deriv_idx] = sf[:, self._deriv_idx]
            # exact power-of-two normalisation
            np.ldexp(f, self._neg_exp, out=f)
            phi, y = np.ascontiguousarray(f[:, 1:]), f[:, 0].copy()
        with np.errstate(over="ignore", invalid="ignore"):
            self._check_finite(phi, y, frame.t)
        return phi, y, frame.t, nonfinite


#: Fewest rows within the speed limits on which :meth:`RegressorBuilder.noise_covariance`
#: takes the slopes of columns that are not linear in a signal.
MIN_NOISE_ROWS = 16


def _nudged(frame: Frame, role: str, by: float, model: ModelView) -> Frame:
    """``frame`` with signal ``role`` moved by ``by`` (the position's angle with it)."""
    v = getattr(frame, role) + by
    if role != "position":
        return dataclasses.replace(frame, **{role: v})
    angle = v if model.axis == "rotary" else Frame.phase(v, model.axis, model.pitch)
    return dataclasses.replace(frame, position=v, angle=angle)
