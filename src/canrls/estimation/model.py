r"""The identification model: which effects, which equations, which regressors.

A :class:`Model` holds the axis, the output, the effects and their options, the
state-variable filter settings, the user terms and the signal ranges. It is validated
once, when built, and then yields its :class:`~canrls.estimation.equation.Equation`\ s:
the mechanical one (whenever a mechanical effect is present) and the electrical one
(when ``electrical`` is), each building its regressors through a stateful
:class:`~canrls.estimation.equation.RegressorBuilder`. The ``[model]`` table, the
regressors, their normalisation and the holds are described in docs/effects.md.
"""

from __future__ import annotations

import logging
import math
import warnings
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from canrls.core.checks import in_range
from canrls.core.errors import ConfigError, EffectError
from canrls.estimation.effects import (
    DEFAULT_BAND,
    DEFAULT_PITCH,
    DEFAULT_STRIBECK_SPEED,
    ELECTRICAL,
    MECHANICAL,
    TERM_KEYS,
    Axis,
    Effect,
    ParameterSpec,
    UserTerm,
    parse_effect,
)
from canrls.estimation.equation import (
    Equation,
)
from canrls.estimation.svf import (
    DEFAULT_CUTOFF_HZ,
    DEFAULT_ZETA,
    ZETA_RANGE,
)

__all__ = ["DATA_OPTIONS", "Model", "DEFAULT_RANGES", "OUTPUTS"]

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
_MODEL_KEYS = ("axis", "pitch", "wrap", "kt", "output", "target", "effects", "filter", "coulomb",
               "stribeck", "terms", "ranges", "scaling")
_HELD_ROLES = ("current", "speed", "position", "voltage", "torque")
#: The mechanical outputs: the current (``Kt*i``, or ``i`` without ``kt``) or the torque
#: (force) the drive reports.
OUTPUTS = ("current", "torque")
#: the key that named the output before ``output`` did (``model.target``, ``{"target": s_y}``
#: in ``model.scaling``): read, with a warning, until the next release
OLD_OUTPUT_KEY = "target"

log = logging.getLogger(__name__)
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


# ---------------------------------------------------------------------------- model
class Model:
    """Effects, output and filter settings; validated once when built.

    :param effects: effect names (``"inertia"``, ``"cogging:24"``, ``"user:NAME"``) or
        :class:`~canrls.estimation.effects.Effect` objects, in column order.
    :param axis: ``"rotary"`` or ``"linear"``.
    :param kt: torque (force) constant; ``None``: the mechanical output is the current.
    :param output: the mechanical output, ``"current"`` (``Kt*i``, or ``i`` without
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
                 kt: float | None = None, output: str = "current",
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
        self.axis: Axis = axis  # type: ignore[assignment]  # one of Axis: checked above
        self.kt = None if kt is None else _number(source, "model.kt", kt, nonzero=True)
        if output not in OUTPUTS:
            raise ConfigError(_fmt(source, "model.output", output,
                                   f"must be one of {', '.join(map(repr, OUTPUTS))}"))
        #: The mechanical output: ``"current"`` or ``"torque"`` (reported by the drive).
        self.output: str = output
        if output == "torque" and self.kt is not None:
            raise ConfigError(_fmt(source, "model.kt", kt,
                                   "the mechanical output is the torque the drive reports "
                                   "(parameters in N·m, or N on a linear axis): Kt is not "
                                   "used; leave it out (or set model.output = \"current\" to "
                                   "identify on the current)"))
        self.pitch = _number(source, "model.pitch", pitch, positive=True)
        self.wrap = None if wrap is None else _number(source, "model.wrap", wrap, positive=True)
        if self.wrap is not None and self.axis == "rotary":
            raise ConfigError(_fmt(source, "model.wrap", wrap,
                                   "only for a linear axis (rotary positions wrap at 2 pi)"))
        self.cutoff_hz = _number(source, "model.filter.cutoff_hz", cutoff_hz, positive=True)
        self.zeta = _number(source, "model.filter.zeta", zeta, positive=True)
        if not in_range(self.zeta, *ZETA_RANGE):
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
            if output == "torque" and "torque" not in av:
                raise ConfigError(_fmt(source, "model.output", output,
                                       "the drive sends no torque signal (map one: "
                                       "torque=MESSAGE.SIGNAL)"))
        self.effects: tuple[Effect, ...] = self._build_effects(effects)
        self.equations: tuple[Equation, ...] = self._build_equations()
        sent = self.available_signals
        for eq in self.equations:
            if sent is not None and eq.name == MECHANICAL and eq.output.signal not in sent:
                raise ConfigError(_fmt(source, "model.output", self.output,
                                       f"the drive sends no {eq.output.signal} signal "
                                       f"(it sends {', '.join(sorted(sent - {'t'}))})"))

    @property
    def target(self) -> str:
        """The old name of :attr:`output`, for one release."""
        warnings.warn("Model.target is now Model.output; the old name goes in the next release",
                      DeprecationWarning, stacklevel=2)
        return self.output

    # -- validation -------------------------------------------------------------------
    @property
    def torque_known(self) -> bool:
        """True when the mechanical output is a torque (``Kt*i`` or the drive's own):
        parameters in N·m (N), not per ampere."""
        return self.kt is not None or self.output == "torque"

    @property
    def per_ampere(self) -> bool:
        """True when the model has a mechanical equation whose output is the raw current
        (no Kt, no torque signal): its mechanical parameters are per ampere."""
        return not self.torque_known and any(e.name == MECHANICAL for e in self.equations)

    @property
    def per_ampere_text(self) -> str:
        """The one line that says so, and how to get N·m (N on a linear axis)."""
        u = "N·m" if self.axis == "rotary" else "N"
        return (f"units: no Kt and no torque signal, so the mechanical parameters are per "
                f"ampere (A where {u} would be): multiply them by Kt [{u}/A] for {u}, or "
                f"give --kt")

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
            bad = sorted(set(t) - TERM_KEYS)
            if bad:
                raise ConfigError(_fmt(src, f"{key}.{bad[0]}", t[bad[0]],
                                       "unknown key (valid: name, "
                                       f"{', '.join(sorted(TERM_KEYS))})"))
            if not isinstance(t.get("expr"), str):
                raise ConfigError(_fmt(src, f"{key}.expr", t.get("expr"),
                                       "required, a string expression"))
            # the table's values as the user wrote them: UserTerm checks each
            options: dict[str, Any] = {
                k: (tuple(v) if k == "range" and isinstance(v, list) else v)
                for k, v in t.items()}
            try:  # compile now so that a bad term fails at load time, even if unused
                UserTerm(name, axis=self.axis, pitch=self.pitch, **options)
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
                                                            '{"output" = s_y, PARAMETER = s}'))
            for name, s in v.items():
                if isinstance(s, bool) or not isinstance(s, int) or not -1000 <= s <= 1000:
                    raise ConfigError(_fmt(self.source, f"{key}.{name}", s,
                                           "must be an integer exponent in [-1000, 1000]"))
            out[k] = {_new_output_key(self.source, f"{key}.{name}", str(name)): int(s)
                      for name, s in v.items()}
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
            for i, eff in enumerate(out):
                if eff.equation == ELECTRICAL:
                    raise EffectError(_fmt(src, f"model.effects[{i}]", eff.name,
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
        output = "" if self.output == "current" else f", output={self.output!r}"
        return (f"Model(effects={[e.name for e in self.effects]}, axis={self.axis!r}, "
                f"kt={self.kt!r}{output}, source={self.source!r})")

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Model) and other.to_dict() == self.to_dict()

    __hash__ = None  # type: ignore[assignment]  # equal by value: no hash, as Python sets it

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
        return dict(axis=self.axis, kt=self.kt, output=self.output, pitch=self.pitch,
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

    def with_search_value(self, key: str, value: float) -> Model:
        """A new model with a searched parameter set (:class:`SearchSpace` ``key``: one of
        :data:`DATA_OPTIONS`, or ``user:NAME:PARAM``, the free parameter of a term)."""
        if key in DATA_OPTIONS:
            return self.with_options(**{key: value})
        term, _, param = key.removeprefix("user:").partition(":")
        if term not in self.terms or not param:
            raise ConfigError(f"{self.source}: with_search_value: {key!r} is no searched "
                              f"parameter of this model")
        kw = self._kwargs()
        kw["terms"] = {**self.terms, term: {**self.terms[term], "search": {param: value}}}
        return Model([e.name for e in self.effects], **kw)

    def with_cutoff(self, cutoff_hz: float) -> Model:
        """The same model with the state-variable filter's cutoff at ``cutoff_hz``."""
        kw = self._kwargs()
        kw["cutoff_hz"] = cutoff_hz
        return Model(self.effects, **kw)

    def with_scaling(self, exponents: Mapping[str, Mapping[str, int]]) -> Model:
        """A new model whose equations use the given power-of-two exponents,
        ``{equation: {"output": s_y, parameter name: s_j}}`` (:attr:`Equation.scaling`),
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
        if self.output != "current":
            d["output"] = self.output
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
        """Build from the contents of a ``[model]`` table (docs/effects.md, *Configuration*)."""
        if not isinstance(d, Mapping):
            raise ConfigError(_fmt(source, "model", d, "must be a table"))
        for k in d:
            if k not in _MODEL_KEYS:
                raise ConfigError(_fmt(source, f"model.{k}", d[k],
                                       f"unknown key (valid: {', '.join(_MODEL_KEYS)})"))
        kw: dict[str, Any] = {}
        if OLD_OUTPUT_KEY in d:
            if "output" in d:
                raise ConfigError(_fmt(source, "model.target", d[OLD_OUTPUT_KEY],
                                       "is the old name of model.output: give one of them"))
            kw["output"] = d[OLD_OUTPUT_KEY]
            _new_output_key(source, "model.target", OLD_OUTPUT_KEY)
        for k in ("axis", "pitch", "wrap", "kt", "output"):
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


def _new_output_key(source: str, where: str, name: str) -> str:
    """``name``, or ``"output"`` for :data:`OLD_OUTPUT_KEY` (with the one-line warning)."""
    if name != OLD_OUTPUT_KEY:
        return name
    if (source, where) not in _WARNED:  # once per file and key: a model is built many times
        _WARNED.add((source, where))
        log.warning("%s: %s is now called output; the old name goes in the next release",
                    source, where)
    return "output"


_WARNED: set[tuple[str, str]] = set()
