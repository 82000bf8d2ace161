r"""The effect library: one class per physical effect of an electric drive.

Each effect adds one or more regressor columns to one equation and yields one
parameter per column. The conventions are those of ``docs/architecture.md``, shared
with the simulated drive:

.. math::

    K_t i = J\dot\omega + B\omega + T_c\,\mathrm{sgn}_\epsilon(\omega)
            + T_s\,\mathrm{sgn}_\epsilon(\omega)\,e^{-(\omega/\omega_s)^2} + T_0
            + T_{g,s}\sin\theta + T_{g,c}\cos\theta
            + \sum_k \left(T_{k,s}\sin k\theta + T_{k,c}\cos k\theta\right)
            + \sum_u c_u f_u

    u = R i + L \frac{di}{dt} + K_e \omega

with :math:`\mathrm{sgn}_\epsilon(\omega) = \tanh(\omega/\epsilon)`. On a linear axis
``omega`` is the speed ``v`` [m/s], the torque a force [N], and the angle of the
periodic terms is :math:`2\pi x / p` with ``p`` the pitch [m]. Without ``kt`` the
mechanical output is the raw current and every mechanical parameter is divided by
``Kt`` (units read ``A`` instead of ``N·m`` or ``N``); a drive that reports its torque
(``torque`` signal) gives the left-hand side itself, :math:`T = J\dot\omega + ...`,
in N·m (N) without ``Kt``.

Every effect class documents its equation, its parameters with units for both axes
and both outputs, the signals it needs, its DBC ``EFFECT_ID`` and its
``RESIDUAL_SIGNATURE``: how its absence shows in the residual, which
:mod:`canrls.diagnosis.analysis` looks for.

Names as the command line gives them are parsed by :func:`parse_effect`:
``inertia``, ``viscous``, ``coulomb``, ``stribeck``, ``offset``, ``unbalance``,
``cogging:K`` (``K`` >= 1 required), ``electrical``, ``user:NAME`` (the term must be
defined in the configuration, passed as ``options["terms"]``).
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

import numpy as np
import numpy.typing as npt

from canrls.core.c_escape import check_text
from canrls.core.effect_names import EffectId, EquationId, parse_effect_name
from canrls.core.errors import EffectError
from canrls.estimation.expr import CompiledExpression, compile_expression
from canrls.estimation.nonlinear import RecordSpan, SearchSpace, log_grid

__all__ = [
    "Axis",
    "Units",
    "Component",
    "Column",
    "Frame",
    "ParameterSpec",
    "Effect",
    "Inertia",
    "Viscous",
    "Coulomb",
    "Stribeck",
    "Offset",
    "Unbalance",
    "Cogging",
    "Electrical",
    "UserTerm",
    "EFFECT_NAMES",
    "EFFECT_IDS",
    "MECHANICAL",
    "ELECTRICAL",
    "OPTION_KEYS",
    "DEFAULT_BAND",
    "DEFAULT_STRIBECK_SPEED",
    "DEFAULT_PITCH",
    "library",
    "parse_effect",
    "effect_spec",
    "output_unit",
]

F64 = npt.NDArray[np.float64]
Axis = Literal["rotary", "linear"]
Range = tuple[float, float]

MECHANICAL = EquationId.MECHANICAL.label
ELECTRICAL = EquationId.ELECTRICAL.label
#: Coulomb smoothing band epsilon [rad/s or m/s].
DEFAULT_BAND = 0.01
#: Stribeck speed omega_s [rad/s or m/s].
DEFAULT_STRIBECK_SPEED = 1.0
#: Linear-axis pitch [m per period of the periodic terms].
DEFAULT_PITCH = 1.0
#: Keys :func:`parse_effect` accepts in ``options`` (each effect reads those it needs).
OPTION_KEYS = frozenset({"axis", "pitch", "band", "speed", "terms"})
#: Keys of one user term definition in ``options["terms"][NAME]``.
TERM_KEYS = frozenset({"expr", "unit", "equation", "range", "search"})


def output_unit(equation: str, axis: Axis = "rotary", kt_known: bool = True) -> str:
    """Unit of an equation's output: ``N·m``/``N`` (torque/force), ``A`` (no Kt), ``V``."""
    if equation == ELECTRICAL:
        return "V"
    if not kt_known:
        return "A"
    return "N·m" if axis == "rotary" else "N"


@dataclass(frozen=True)
class Units:
    """A parameter's unit on each axis, with Kt known and (``*_current``) unknown."""

    rotary: str
    linear: str
    rotary_current: str | None = None
    linear_current: str | None = None

    def get(self, axis: Axis = "rotary", kt_known: bool = True) -> str:
        if axis == "rotary":
            return self.rotary if kt_known or self.rotary_current is None else self.rotary_current
        return self.linear if kt_known or self.linear_current is None else self.linear_current


_TORQUE = Units("N·m", "N", "A", "A")


@dataclass(frozen=True)
class Component:
    """One parameter of an effect: its symbol, description and units."""

    symbol: str
    description: str
    linear_description: str
    units: Units


@dataclass(frozen=True)
class Column:
    """One raw regressor column.

    ``raw(frame)`` returns the column's values, or for a ``derivative`` column the
    signal whose time derivative the column is (the model filters it through ``sF``).
    ``range(ranges)`` gives ``(lo, hi)`` of what ``raw`` returns, for normalisation;
    ``rate`` names the range of a derivative column's derivative (``"acceleration"``,
    ``"current_rate"``), used when configured. ``reads`` lists the signal roles the
    column is computed from (the model filters it with a zero-order hold when one of
    them is a held signal).
    """

    symbol: str
    derivative: bool
    raw: Callable[[Frame], F64]
    range: Callable[[Mapping[str, Range]], Range]
    rate: str | None = None
    reads: frozenset[str] = frozenset()


@dataclass(frozen=True)
class ParameterSpec:
    """What one estimated parameter is (name per the architecture, unit, origin).

    ``component``, ``order`` and ``equation_index`` are the ``Component``, ``Order`` and
    ``Equation`` fields of the ``RlsParamInfo`` frame.
    """

    name: str
    symbol: str
    unit: str
    description: str
    effect: str
    effect_id: int
    component: int
    order: int
    equation: str

    @property
    def equation_index(self) -> EquationId:
        """MECHANICAL (0) or ELECTRICAL (1): the DBC ``Equation`` of :attr:`equation`."""
        return EquationId.from_label(self.equation)


@dataclass(frozen=True)
class Frame:
    """The signals an effect reads, in SI units, all of one block length.

    ``position`` is the unwrapped position; ``angle`` the phase of periodic terms
    (rotary: the position itself, linear: ``2 pi (x mod pitch) / pitch``).
    """

    t: F64
    current: F64 | None
    speed: F64
    position: F64 | None = None
    voltage: F64 | None = None
    angle: F64 | None = None
    torque: F64 | None = None

    @staticmethod
    def phase(position: F64, axis: Axis, pitch: float) -> F64:
        """The angle of the periodic terms for a (possibly unwrapped) position."""
        if axis == "rotary":
            return position
        # 2 pi x / pitch, reduced first (fmod is exact) to keep precision far from 0
        return (2.0 * math.pi / pitch) * np.fmod(position, pitch)

    @classmethod
    def from_signals(cls, signals: Any, axis: Axis = "rotary",
                     pitch: float = DEFAULT_PITCH) -> Frame:
        """Wrap a :class:`~canrls.core.samples.Signals` block (its position taken as given)."""
        def col(v: Any) -> F64:
            return np.ascontiguousarray(v, dtype=np.float64)

        def arr(v: Any) -> F64 | None:
            return None if v is None else col(v)

        pos = arr(getattr(signals, "position", None))
        return cls(t=col(signals.t), current=arr(getattr(signals, "current", None)),
                   speed=col(signals.speed), position=pos,
                   voltage=arr(getattr(signals, "voltage", None)),
                   angle=None if pos is None else cls.phase(pos, axis, pitch),
                   torque=arr(getattr(signals, "torque", None)))

    def get(self, role: str) -> F64:
        v = getattr(self, role, None)
        if v is None:
            raise EffectError(f"signal {role!r} is not available in this block")
        return v


def _need(frame: Frame, role: str, effect: str) -> F64:
    v = getattr(frame, role, None)
    if v is None:
        raise EffectError(f"effect {effect!r} needs signal {role!r}, which is not available")
    return v


def _role_range(role: str) -> Callable[[Mapping[str, Range]], Range]:
    def rng(ranges: Mapping[str, Range]) -> Range:
        r = ranges.get(role)
        if r is None:
            return (-math.inf, math.inf)
        return (float(r[0]), float(r[1]))

    return rng


def _const_range(lo: float, hi: float) -> Callable[[Mapping[str, Range]], Range]:
    return lambda ranges: (lo, hi)


def _positive_option(effect: str, key: str, value: Any) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError) as e:
        raise EffectError(f"effect {effect!r}: option {key} = {value!r} is not a number") from e
    if isinstance(value, bool) or not math.isfinite(v) or v <= 0.0:
        raise EffectError(f"effect {effect!r}: option {key} = {value!r} must be a number > 0")
    return v


class Effect:
    """Base class: one physical effect, its columns and its parameters.

    Subclasses set the class attributes below and implement :meth:`columns`. Instances
    are immutable and compare equal when they have the same name and options.
    """

    #: Base name on the command line.
    NAME: ClassVar[str] = ""
    #: Identifier in the DBC (``EffectId``).
    EFFECT_ID: ClassVar[EffectId] = EffectId.NONE
    #: Which equation the effect belongs to (``"mechanical"`` or ``"electrical"``).
    EQUATION: ClassVar[str] = MECHANICAL
    #: The term, as text.
    EQUATION_TEXT: ClassVar[str] = ""
    #: How the absence of this effect shows in the residual.
    RESIDUAL_SIGNATURE: ClassVar[str] = ""
    #: What a rise of its parameters (or the effect appearing) means on a drive in
    #: service, what a fall means, and what to check: the fleet's alerts say these.
    CHANGE_CAUSE: ClassVar[tuple[str, str]] = ("", "")
    CHANGE_CHECK: ClassVar[str] = ""
    #: The parameters, one per column.
    COMPONENTS: ClassVar[tuple[Component, ...]] = ()
    #: Signal roles the effect reads.
    REQUIRES: ClassVar[frozenset[str]] = frozenset()

    def __init__(self, *, axis: Axis = "rotary", pitch: float = DEFAULT_PITCH) -> None:
        if axis not in ("rotary", "linear"):
            raise EffectError(
                f"effect {self.NAME!r}: option axis = {axis!r} must be 'rotary' or 'linear'")
        self.axis: Axis = axis
        self.pitch = _positive_option(self.NAME, "pitch", pitch)

    # -- identity -------------------------------------------------------------------
    @property
    def name(self) -> str:
        """The effect's name as the command line gives it (``cogging:24``)."""
        return self.NAME

    @property
    def order(self) -> int:
        """Harmonic order in position (cogging ``k``, unbalance 1, otherwise 0)."""
        return 0

    @property
    def equation(self) -> str:
        return self.EQUATION

    @property
    def effect_id(self) -> int:
        return self.EFFECT_ID

    @property
    def requires(self) -> frozenset[str]:
        """Signal roles this effect needs (beyond the output's)."""
        return self.REQUIRES

    @property
    def components(self) -> tuple[Component, ...]:
        return self.COMPONENTS

    def _options(self) -> tuple[tuple[str, Any], ...]:
        return (("axis", self.axis), ("pitch", self.pitch))

    def __eq__(self, other: object) -> bool:
        return (type(other) is type(self) and isinstance(other, Effect)
                and other.name == self.name and other._options() == self._options())

    def __hash__(self) -> int:
        return hash((type(self), self.name, self._options()))

    def __repr__(self) -> str:
        opts = ", ".join(f"{k}={v!r}" for k, v in self._options())
        return f"{type(self).__name__}({self.name!r}, {opts})"

    # -- regression -----------------------------------------------------------------
    def columns(self) -> tuple[Column, ...]:
        """The raw regressor columns, one per parameter, in component order."""
        raise NotImplementedError

    def search_space(self, span: RecordSpan) -> tuple[SearchSpace, ...]:
        """The parameters of this effect that the regression cannot estimate linearly,
        with the values a record spanning ``span`` can tell apart (none by default)."""
        return ()

    def parameters(self, kt_known: bool = True) -> tuple[ParameterSpec, ...]:
        """The parameter this effect yields per column, with units for this axis."""
        out = []
        for idx, c in enumerate(self.components):
            desc = c.description if self.axis == "rotary" else c.linear_description
            out.append(ParameterSpec(
                name=f"{self.name}.{c.symbol}", symbol=c.symbol,
                unit=c.units.get(self.axis, kt_known), description=desc, effect=self.name,
                effect_id=self.effect_id, component=idx, order=self.order,
                equation=self.equation))
        return tuple(out)

    def evaluate(self, params: Mapping[str, float], signals: Any) -> F64:
        """This effect's contribution to its equation's output for given parameters.

        ``params`` maps parameter names (``"coulomb.Tc"``; a bare symbol ``"Tc"`` is
        accepted too) to values in the units of :meth:`parameters`. ``signals`` is a
        :class:`~canrls.core.samples.Signals` block or a :class:`Frame`; derivative terms use
        ``np.gradient`` against ``t``; the position is used as given (pass it unwrapped
        when a user term uses ``theta`` other than periodically). For checks and
        simulation cross-tests, not the estimation path.
        """
        frame = signals if isinstance(signals, Frame) else Frame.from_signals(
            signals, self.axis, self.pitch)
        n = len(frame.t)
        out = np.zeros(n)
        for col in self.columns():
            p = self._param(params, col.symbol)
            x = col.raw(frame)
            if col.derivative:
                x = np.gradient(x, frame.t) if n > 1 else np.zeros(n)
            out = out + p * x
        return out

    def _param(self, params: Mapping[str, float], symbol: str) -> float:
        for key in (f"{self.name}.{symbol}", symbol):
            if key in params:
                return float(params[key])
        raise EffectError(
            f"effect {self.name!r}: no value for parameter {self.name}.{symbol} "
            f"(given: {sorted(params)})")

    @classmethod
    def describe(cls) -> str:
        """A plain-text summary: equation, parameters and units, signals, signature."""
        lines = [f"{cls.NAME} (id {cls.EFFECT_ID}, {cls.EQUATION} equation): "
                 f"{cls.EQUATION_TEXT}"]
        for c in cls.COMPONENTS:
            u = c.units
            cur = (f"; without Kt: [{u.rotary_current}], linear [{u.linear_current}]"
                   if u.rotary_current else "")
            lines.append(f"  {c.symbol}: {c.description} [{u.rotary}] "
                         f"(linear: {c.linear_description} [{u.linear}]{cur})")
        req = ", ".join(sorted(cls.REQUIRES)) or "none beyond the output"
        lines.append(f"  needs: {req}")
        lines.append(f"  missing shows as: {cls.RESIDUAL_SIGNATURE}")
        return "\n".join(lines)


class Inertia(Effect):
    r"""Inertia: the torque that accelerates the rotor and load.

    .. math:: \tau = J \frac{d\omega}{dt}

    One derivative column (the speed, differentiated through ``sF``). Parameter
    ``inertia.J``: moment of inertia [kg·m²]; linear axis: moving mass [kg]. Without
    Kt: [A·s²/rad] / [A·s²/m].
    """

    NAME = "inertia"
    EFFECT_ID = EffectId.INERTIA
    EQUATION_TEXT = "J * domega/dt"
    RESIDUAL_SIGNATURE = ("residual correlated with the acceleration domega/dt: largest "
                          "while speeding up or slowing down, zero at constant speed")
    CHANGE_CAUSE = ("more inertia: a changed or added load, a coupling or gear replaced",
                    "less inertia: a load removed or decoupled (a slipping or broken coupling)")
    CHANGE_CHECK = "the load and its coupling; the speed loop, tuned on the old inertia"
    COMPONENTS = (Component("J", "moment of inertia", "moving mass",
                            Units("kg·m²", "kg", "A·s²/rad", "A·s²/m")),)
    REQUIRES = frozenset({"speed"})

    def columns(self) -> tuple[Column, ...]:
        return (Column("J", True, lambda f: _need(f, "speed", self.name), _role_range("speed"),
                       rate="acceleration", reads=self.REQUIRES),)


class Viscous(Effect):
    r"""Viscous friction: a drag proportional to speed.

    .. math:: \tau = B \omega

    Parameter ``viscous.B`` [N·m·s/rad]; linear [N·s/m]; without Kt [A·s/rad] / [A·s/m].
    """

    NAME = "viscous"
    EFFECT_ID = EffectId.VISCOUS
    EQUATION_TEXT = "B * omega"
    RESIDUAL_SIGNATURE = ("residual linear in speed and odd: proportional to omega, "
                          "changing sign with the direction")
    CHANGE_CAUSE = ("more viscous friction: lubricant degraded, thickened or cold, a seal dragging",
                    "less viscous friction: a warmer or thinner lubricant, a seal worn through")
    CHANGE_CHECK = "the lubricant (grade, level, temperature) and the seals"
    COMPONENTS = (Component("B", "viscous friction coefficient",
                            "viscous friction coefficient",
                            Units("N·m·s/rad", "N·s/m", "A·s/rad", "A·s/m")),)
    REQUIRES = frozenset({"speed"})

    def columns(self) -> tuple[Column, ...]:
        return (Column("B", False, lambda f: _need(f, "speed", self.name),
                       _role_range("speed"), reads=self.REQUIRES),)


class Coulomb(Effect):
    r"""Coulomb friction: a constant torque opposing the motion.

    .. math:: \tau = T_c\,\mathrm{sgn}_\epsilon(\omega), \qquad
              \mathrm{sgn}_\epsilon(\omega) = \tanh(\omega / \epsilon)

    ``epsilon`` is the smoothing band (option ``band``, default 0.01 rad/s or m/s).
    Parameter ``coulomb.Tc`` [N·m]; linear [N]; without Kt [A]. ``Tc > 0``.
    """

    NAME = "coulomb"
    EFFECT_ID = EffectId.COULOMB
    EQUATION_TEXT = "Tc * tanh(omega / band)"
    RESIDUAL_SIGNATURE = ("a step in the residual at zero speed whose sign follows the "
                          "direction of motion, constant in magnitude away from zero")
    CHANGE_CAUSE = ("more Coulomb friction: bearing or seal wear, lubrication",
                    "less Coulomb friction: a seal worn through or a load lightened")
    CHANGE_CHECK = "the bearings and seals, the lubrication"
    COMPONENTS = (Component("Tc", "Coulomb friction torque", "Coulomb friction force",
                            _TORQUE),)
    REQUIRES = frozenset({"speed"})

    def __init__(self, *, band: float = DEFAULT_BAND, axis: Axis = "rotary",
                 pitch: float = DEFAULT_PITCH) -> None:
        super().__init__(axis=axis, pitch=pitch)
        self.band = _positive_option(self.NAME, "band", band)

    def _options(self) -> tuple[tuple[str, Any], ...]:
        return (*super()._options(), ("band", self.band))

    def sgn(self, w: F64) -> F64:
        """The smoothed sign ``tanh(omega / band)``."""
        return np.tanh(w / self.band)

    def search_space(self, span: RecordSpan) -> tuple[SearchSpace, ...]:
        """The band, from half the speed noise to 16 times it (at most half the lowest
        speed moved at, where the sign is no longer in doubt)."""
        lo = 0.5 * span.speed_noise
        hi = max(lo, min(16.0 * span.speed_noise, 0.5 * span.speed_high))
        grid = log_grid(lo, hi) if lo > 0 else ()
        return (SearchSpace("coulomb_band", "Coulomb band", span.speed_unit, grid,
                            self.band),)

    def columns(self) -> tuple[Column, ...]:
        return (Column("Tc", False, lambda f: self.sgn(_need(f, "speed", self.name)),
                       _const_range(-1.0, 1.0), reads=self.REQUIRES),)


class Stribeck(Effect):
    r"""Stribeck friction: extra breakaway friction near zero speed.

    .. math:: \tau = T_s\,\mathrm{sgn}_\epsilon(\omega)\,e^{-(\omega/\omega_s)^2}

    ``omega_s`` is the Stribeck speed (option ``speed``, default 1.0 rad/s or m/s),
    ``epsilon`` the Coulomb band (option ``band``). Parameter ``stribeck.Ts`` [N·m];
    linear [N]; without Kt [A].
    """

    NAME = "stribeck"
    EFFECT_ID = EffectId.STRIBECK
    EQUATION_TEXT = "Ts * tanh(omega / band) * exp(-(omega / speed)**2)"
    RESIDUAL_SIGNATURE = ("a bump near zero speed, signed with the direction, decaying "
                          "with |omega| over the Stribeck speed")
    CHANGE_CAUSE = ("more breakaway friction: stick-slip from lubrication or a guide contaminated",
                    "less breakaway friction")
    CHANGE_CHECK = "the lubrication at low speed, guides and ways"
    COMPONENTS = (Component("Ts", "Stribeck (breakaway) friction torque",
                            "Stribeck (breakaway) friction force", _TORQUE),)
    REQUIRES = frozenset({"speed"})

    def __init__(self, *, band: float = DEFAULT_BAND, speed: float = DEFAULT_STRIBECK_SPEED,
                 axis: Axis = "rotary", pitch: float = DEFAULT_PITCH) -> None:
        super().__init__(axis=axis, pitch=pitch)
        self.band = _positive_option(self.NAME, "band", band)
        self.speed = _positive_option(self.NAME, "speed", speed)

    def _options(self) -> tuple[tuple[str, Any], ...]:
        return (*super()._options(), ("band", self.band), ("speed", self.speed))

    def search_space(self, span: RecordSpan) -> tuple[SearchSpace, ...]:
        """The Stribeck speed, on a log grid over the speeds the record covers: not
        below the band (a bump narrower than the smoothed sign is no bump), not above a
        third of the median speed: at 3 ``speed`` the bump is down to 1e-4, and at
        least half the record must lie beyond it, or a bump wider than the speeds moved
        at, ``sgn(w) (1 - (w/speed)^2 ...)``, is Coulomb friction plus any odd
        nonlinearity in speed (a fan load ``w |w|``)."""
        lo, hi = max(span.speed_low, self.band), span.speed_mid / 3.0
        grid = log_grid(lo, hi) if 0 < lo < hi else ()
        return (SearchSpace("stribeck_speed", "Stribeck speed", span.speed_unit, grid,
                            self.speed),)

    def shape(self, w: F64) -> F64:
        """``tanh(omega / band) * exp(-(omega / speed)^2)``."""
        r = w / self.speed
        return np.tanh(w / self.band) * np.exp(-(r * r))

    def columns(self) -> tuple[Column, ...]:
        return (Column("Ts", False, lambda f: self.shape(_need(f, "speed", self.name)),
                       _const_range(-1.0, 1.0), reads=self.REQUIRES),)


class Offset(Effect):
    r"""Torque offset: a constant, e.g. a current-sensor offset or gravity on a hoist.

    .. math:: \tau = T_0

    Parameter ``offset.T0`` [N·m]; linear [N]; without Kt [A].
    """

    NAME = "offset"
    EFFECT_ID = EffectId.OFFSET
    EQUATION_TEXT = "T0"
    RESIDUAL_SIGNATURE = ("a constant non-zero mean of the residual, independent of "
                          "speed, direction and position")
    CHANGE_CAUSE = ("a larger torque offset: a load that pulls one way (gravity, a process "
                    "force) or a current-sensor offset",
                    "a smaller torque offset")
    CHANGE_CHECK = "the process load and the current sensor's zero"
    COMPONENTS = (Component("T0", "torque offset", "force offset", _TORQUE),)
    REQUIRES = frozenset()

    def columns(self) -> tuple[Column, ...]:
        return (Column("T0", False, lambda f: np.ones(len(f.t)), _const_range(1.0, 1.0)),)


class _Periodic(Effect):
    """sin/cos pair at a harmonic order of the position angle."""

    def _order(self) -> int:
        return 1

    def columns(self) -> tuple[Column, ...]:
        k = float(self._order())

        def ang(f: Frame) -> F64:
            a = f.angle
            if a is None:
                p = _need(f, "position", self.name)
                a = Frame.phase(p, self.axis, self.pitch)
            return a if k == 1.0 else k * a

        return (Column("sin", False, lambda f: np.sin(ang(f)), _const_range(-1.0, 1.0),
                       reads=self.REQUIRES),
                Column("cos", False, lambda f: np.cos(ang(f)), _const_range(-1.0, 1.0),
                       reads=self.REQUIRES))


class Unbalance(_Periodic):
    r"""Unbalance: a torque that repeats once per revolution (gravity on an eccentric mass).

    .. math:: \tau = T_{g,s}\sin\theta + T_{g,c}\cos\theta

    Linear axis: :math:`\theta = 2\pi x / p` (once per pitch ``p``). Parameters
    ``unbalance.sin``, ``unbalance.cos`` [N·m]; linear [N]; without Kt [A].
    """

    NAME = "unbalance"
    EFFECT_ID = EffectId.UNBALANCE
    EQUATION_TEXT = "Tg_sin * sin(theta) + Tg_cos * cos(theta)"
    RESIDUAL_SIGNATURE = ("order 1 in position: the residual repeats once per revolution "
                          "(once per pitch on a linear axis), a peak at rotation order 1 "
                          "of the residual spectrum")
    CHANGE_CAUSE = ("a new or larger once-per-revolution torque: an unbalance or an "
                    "eccentric load, a mechanical change at order 1",
                    "a once-per-revolution torque smaller")
    CHANGE_CHECK = "the rotor and load for unbalance or eccentricity, the mounting"
    COMPONENTS = (Component("sin", "unbalance torque, sine component",
                            "unbalance force, sine component", _TORQUE),
                  Component("cos", "unbalance torque, cosine component",
                            "unbalance force, cosine component", _TORQUE))
    REQUIRES = frozenset({"position"})

    @property
    def order(self) -> int:
        return 1


class Cogging(_Periodic):
    r"""Cogging torque at harmonic order ``k``: ``k`` periods per revolution.

    .. math:: \tau = T_{k,s}\sin k\theta + T_{k,c}\cos k\theta

    Named ``cogging:K`` (``K`` >= 1, e.g. the slot count or the LCM of slots and
    poles). Linear axis: ``k`` periods per pitch. Parameters ``cogging:K.sin``,
    ``cogging:K.cos`` [N·m]; linear [N]; without Kt [A].
    """

    NAME = "cogging"
    EFFECT_ID = EffectId.COGGING
    EQUATION_TEXT = "Tk_sin * sin(k * theta) + Tk_cos * cos(k * theta)"
    RESIDUAL_SIGNATURE = ("a peak at rotation order k of the residual spectrum (k periods "
                          "per revolution, per pitch on a linear axis)")
    CHANGE_CAUSE = ("a new or larger torque at this order of the revolution: a mechanical "
                    "change at that order (a bearing, a gear mesh, a magnet)",
                    "a torque at this order smaller")
    CHANGE_CHECK = "the bearings and gears whose order matches, the magnets"
    COMPONENTS = (Component("sin", "cogging torque, sine component",
                            "cogging force, sine component", _TORQUE),
                  Component("cos", "cogging torque, cosine component",
                            "cogging force, cosine component", _TORQUE))
    REQUIRES = frozenset({"position"})

    def __init__(self, k: int, *, axis: Axis = "rotary", pitch: float = DEFAULT_PITCH) -> None:
        super().__init__(axis=axis, pitch=pitch)
        if isinstance(k, bool) or not isinstance(k, int | np.integer) or k < 1:
            raise EffectError(f"effect 'cogging:{k}': order K = {k!r} must be an integer >= 1")
        self.k = int(k)

    def _order(self) -> int:
        return self.k

    @property
    def order(self) -> int:
        return self.k

    @property
    def name(self) -> str:
        return f"cogging:{self.k}"


class Electrical(Effect):
    r"""The electrical (q-axis voltage) equation: resistance, inductance and back-EMF.

    .. math:: u = R i + L \frac{di}{dt} + K_e \omega

    Needs the voltage signal. Parameters ``electrical.R`` [Ohm], ``electrical.L`` [H],
    ``electrical.Ke`` [V·s/rad] (linear [V·s/m]); the output is the voltage whatever
    Kt is.
    """

    NAME = "electrical"
    EFFECT_ID = EffectId.ELECTRICAL
    EQUATION = ELECTRICAL
    EQUATION_TEXT = "u = R * i + L * di/dt + Ke * omega"
    RESIDUAL_SIGNATURE = ("in the voltage equation: a residual proportional to the current "
                          "(R), peaking at current steps (L, di/dt) and linear in speed "
                          "(Ke, back-EMF)")
    CHANGE_CAUSE = ("a larger electrical parameter: a hotter or damaged winding, a loose "
                    "connection",
                    "a smaller electrical parameter: a short between turns, weakened magnets "
                    "(back-EMF)")
    CHANGE_CHECK = "the winding temperature and resistance, the connections, the magnets"
    COMPONENTS = (
        Component("R", "winding resistance", "winding resistance", Units("Ohm", "Ohm")),
        Component("L", "winding inductance", "winding inductance", Units("H", "H")),
        Component("Ke", "back-EMF constant", "back-EMF constant", Units("V·s/rad", "V·s/m")),
    )
    REQUIRES = frozenset({"current", "speed", "voltage"})

    def columns(self) -> tuple[Column, ...]:
        return (
            Column("R", False, lambda f: _need(f, "current", self.name), _role_range("current"),
                   reads=frozenset({"current"})),
            Column("L", True, lambda f: _need(f, "current", self.name), _role_range("current"),
                   rate="current_rate", reads=frozenset({"current"})),
            Column("Ke", False, lambda f: _need(f, "speed", self.name), _role_range("speed"),
                   reads=frozenset({"speed"})),
        )


_SIMPLE_UNIT = re.compile(r"^[^\s/*·]+$")


class UserTerm(Effect):
    r"""A user-defined term: a coefficient times an expression of the signals.

    .. math:: \tau = c_u\, f_u(\omega, \theta, i, u, t)

    ``f_u`` is compiled by :func:`canrls.estimation.expr.compile_expression` from the term's
    ``expr``. Options: ``expr`` (required), ``unit`` of ``f_u`` (default ``"1"``),
    ``equation`` (``"mechanical"`` default, or ``"electrical"``), ``range = [lo, hi]`` of
    ``f_u`` for normalisation (default: derived from the signal ranges by interval
    arithmetic), ``search = {PARAM: [lo, hi]}`` (or ``{PARAM: value}``, kept): one free
    parameter of ``expr`` that the regression cannot estimate linearly, searched by the
    diagnosis. Parameter ``user:NAME.c`` in the output unit divided by ``unit``.
    """

    NAME = "user"
    EFFECT_ID = EffectId.USER
    EQUATION_TEXT = "c * f(signals)"
    RESIDUAL_SIGNATURE = ("the residual follows the user function f(signals): it "
                          "correlates with the term's own column")
    CHANGE_CAUSE = ("the user term changed", "the user term changed")
    CHANGE_CHECK = "what the user term models"
    COMPONENTS = (Component("c", "user term coefficient", "user term coefficient",
                            Units("N·m/unit", "N/unit", "A/unit", "A/unit")),)
    REQUIRES = frozenset()

    def __init__(self, term: str, *, expr: str, unit: str = "1", equation: str = MECHANICAL,
                 range: tuple[float, float] | None = None,
                 search: Mapping[str, Any] | None = None, axis: Axis = "rotary",
                 pitch: float = DEFAULT_PITCH) -> None:
        super().__init__(axis=axis, pitch=pitch)
        if not isinstance(term, str) or not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", term):
            raise EffectError(f"effect 'user:{term}': term name {term!r} must be an identifier")
        self.term = term
        if equation not in (MECHANICAL, ELECTRICAL):
            raise EffectError(f"effect 'user:{term}': equation = {equation!r} must be "
                              f"'{MECHANICAL}' or '{ELECTRICAL}'")
        self._equation = equation
        # one line of printable text: the unit goes into reports and generated C
        self.unit = check_text(unit, f"effect 'user:{term}': unit", EffectError).strip() or "1"
        self.range: tuple[float, float] | None = None
        if range is not None:
            # [lo, hi]: a list or tuple of two real numbers (not a table, string or bool)
            ok = (isinstance(range, list | tuple) and len(range) == 2
                  and all(isinstance(x, int | float) and not isinstance(x, bool)
                          and (not isinstance(x, int) or x.bit_length() <= 1023)
                          for x in range))
            if ok:
                lo, hi = float(range[0]), float(range[1])
                ok = math.isfinite(lo) and math.isfinite(hi) and lo <= hi
            if not ok:
                raise EffectError(f"effect 'user:{term}': range = {range!r} must be "
                                  f"[lo, hi] with finite lo <= hi")
            self.range = (lo, hi)
        #: The free parameter: ``(name, (lo, hi))`` searched, or ``(name, value)`` set
        #: in the configuration (kept); None without one.
        self.free: tuple[str, tuple[float, float] | float] | None = _free_parameter(
            term, search)
        values = {} if self.free is None else {self.free[0]: self.free_value}
        self.expression: CompiledExpression = compile_expression(expr, name=term,
                                                                 parameters=values)
        self.expr = self.expression.text
        if self.free is not None and self.free[0] not in self.expression.parameters:
            raise EffectError(f"effect 'user:{term}': search names {self.free[0]!r}, which "
                              f"the expression {self.expr!r} does not use")

    @property
    def free_value(self) -> float:
        """The free parameter's value: the one set, else the middle of its range (in
        log where the range keeps one sign)."""
        assert self.free is not None
        v = self.free[1]
        if isinstance(v, tuple):
            lo, hi = v
            return math.copysign(math.sqrt(lo * hi), lo) if lo * hi > 0 else 0.5 * (lo + hi)
        return v

    def _options(self) -> tuple[tuple[str, Any], ...]:
        return (*super()._options(), ("expr", self.expr), ("unit", self.unit),
                ("equation", self._equation), ("range", self.range), ("free", self.free))

    def search_space(self, span: RecordSpan) -> tuple[SearchSpace, ...]:
        """The free parameter over its configured ``[lo, hi]`` (none when set to a value)."""
        if self.free is None:
            return ()
        p, v = self.free
        grid = log_grid(*v) if isinstance(v, tuple) else ()
        return (SearchSpace(f"{self.name}:{p}", f"{self.name} {p}", "", grid,
                            self.free_value, not isinstance(v, tuple)),)

    @property
    def name(self) -> str:
        return f"user:{self.term}"

    @property
    def equation(self) -> str:
        return self._equation

    @property
    def requires(self) -> frozenset[str]:
        return frozenset(self.expression.signals) - {"t"}

    def parameters(self, kt_known: bool = True) -> tuple[ParameterSpec, ...]:
        tu = output_unit(self._equation, self.axis, kt_known)
        if self.unit == "1":
            unit = tu
        elif _SIMPLE_UNIT.match(self.unit):
            unit = f"{tu}/{self.unit}"
        else:
            unit = f"{tu}/({self.unit})"
        return (ParameterSpec(
            name=f"{self.name}.c", symbol="c", unit=unit,
            description=f"coefficient of user term {self.term}: {self.expr}",
            effect=self.name, effect_id=self.EFFECT_ID, component=0, order=0,
            equation=self._equation),)

    def columns(self) -> tuple[Column, ...]:
        def rng(ranges: Mapping[str, Range]) -> Range:
            if self.range is not None:
                return self.range
            return self.expression.bounds(ranges)

        return (Column("c", False, lambda f: self.expression(f), rng,
                       reads=frozenset(self.expression.signals)),)


def _free_parameter(term: str, search: Any) -> tuple[str, tuple[float, float] | float] | None:
    """A user term's ``search``: one ``{NAME = [lo, hi]}`` (searched) or ``{NAME = value}``
    (kept), checked."""
    if search is None:
        return None
    what = f"effect 'user:{term}': search"
    if not isinstance(search, Mapping) or len(search) != 1:
        raise EffectError(f"{what} = {search!r} must be a table of one free parameter, "
                          f"e.g. {{ c = [0.005, 0.5] }}")
    (name, v), = search.items()

    def real(x: Any) -> bool:
        return (isinstance(x, int | float) and not isinstance(x, bool)
                and math.isfinite(float(x)))

    if isinstance(v, list | tuple) and len(v) == 2 and all(real(x) for x in v) \
            and float(v[0]) < float(v[1]) and float(v[0]) * float(v[1]) > 0:
        return str(name), (float(v[0]), float(v[1]))
    if real(v):
        return str(name), float(v)
    raise EffectError(f"{what}.{name} = {v!r} must be [lo, hi] with finite lo < hi of one "
                      f"sign (searched) or a number (kept)")


_CLASSES: tuple[type[Effect], ...] = (Inertia, Viscous, Coulomb, Stribeck, Offset, Unbalance,
                                      Cogging, Electrical, UserTerm)
#: Base effect names, in ``EFFECT_ID`` order.
EFFECT_NAMES: tuple[str, ...] = tuple(c.NAME for c in _CLASSES)
#: Base name -> DBC ``EffectId``.
EFFECT_IDS: Mapping[str, int] = {c.NAME: c.EFFECT_ID for c in _CLASSES}


def library() -> tuple[type[Effect], ...]:
    """Every effect class, in ``EFFECT_ID`` order (each carries its documentation)."""
    return _CLASSES


def effect_spec(effect_id: int, order: int = 0) -> str:
    """The command-line name of an effect given its DBC id (and order for cogging).

    User terms (id 9) cannot be named by id alone and raise :class:`EffectError`.
    """
    for cls in _CLASSES:
        if cls.EFFECT_ID == effect_id:
            if cls is Cogging:
                if order < 1:
                    raise EffectError(f"effect id 7 (cogging): order = {order!r} must be >= 1")
                return f"cogging:{order}"
            if cls is UserTerm:
                raise EffectError("effect id 9 (user): a user term is named, not numbered; "
                                  "use user:NAME")
            return cls.NAME
    raise EffectError(f"unknown effect id {effect_id!r}; valid ids: "
                      + ", ".join(f"{c.EFFECT_ID} ({c.NAME})" for c in _CLASSES))


def parse_effect(spec: str, options: Mapping[str, Any] | None = None) -> Effect:
    """Build an effect from its command-line name.

    :param spec: ``inertia``, ``viscous``, ``coulomb``, ``stribeck``, ``offset``,
        ``unbalance``, ``cogging:K``, ``electrical`` or ``user:NAME``.
    :param options: shared options, each effect reading those it uses: ``axis``
        (``"rotary"``/``"linear"``), ``pitch`` [m], ``band`` (Coulomb/Stribeck smoothing),
        ``speed`` (Stribeck speed), ``terms`` (``{NAME: {"expr": ..., "unit": ...,
        "equation": ..., "range": [lo, hi], "search": {PARAM: [lo, hi]}}}`` for user
        terms).
    :raises EffectError: unknown effect (the message lists the valid names), missing or
        bad order, undefined user term, or an invalid option value.
    """
    opts = dict(options or {})
    unknown = sorted(set(opts) - OPTION_KEYS)
    if unknown:
        raise EffectError(f"effect {spec!r}: unknown option(s) {unknown}; "
                          f"valid options: {sorted(OPTION_KEYS)}")
    common: dict[str, Any] = {k: opts[k] for k in ("axis", "pitch") if k in opts}
    name = parse_effect_name(spec)
    if name.effect is EffectId.COGGING:
        return Cogging(name.order, **common)
    if name.effect is EffectId.USER:
        arg = name.term
        terms = opts.get("terms") or {}
        if arg not in terms:
            defined = ", ".join(sorted(terms)) or "none"
            raise EffectError(f"effect {spec!r}: user term {arg!r} is not defined "
                              f"(defined terms: {defined})")
        t = terms[arg]
        if not isinstance(t, Mapping):
            raise EffectError(f"effect {spec!r}: term definition {t!r} must be a table")
        bad = sorted(set(t) - TERM_KEYS - {"name"})
        if bad:
            raise EffectError(f"effect {spec!r}: unknown term key(s) {bad}; "
                              f"valid keys: {sorted(TERM_KEYS)}")
        if "expr" not in t:
            raise EffectError(f"effect {spec!r}: term {arg!r} has no 'expr'")
        kw = {k: t[k] for k in ("unit", "equation", "range", "search") if k in t}
        return UserTerm(arg, expr=t["expr"], **kw, **common)
    if name.effect is EffectId.COULOMB:
        return Coulomb(**common, **{k: opts[k] for k in ("band",) if k in opts})
    if name.effect is EffectId.STRIBECK:
        return Stribeck(**common, **{k: opts[k] for k in ("band", "speed") if k in opts})
    cls = {c.EFFECT_ID: c for c in _CLASSES}[name.effect]
    return cls(**common)
