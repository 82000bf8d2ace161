"""Conversion of DBC unit strings to SI, per signal role.

A DBC states the physical unit of each signal as free text (``"A"``, ``"rpm"``,
``"deg"``...). canrls works in SI (:mod:`canrls.core.samples`): current in A, speed in
rad/s (linear axis: m/s), position in rad (linear axis: m), voltage in V, a torque
reported by the drive in N·m (linear axis: a force in N). This module maps a unit
string to the factor that turns a DBC physical value into SI::

    value_SI = factor * value_DBC

>>> si_factor("speed", "rpm")  # 2*pi/60
0.10471975511965977
>>> si_factor("current", "mA")
0.001
>>> si_factor("speed", "0.1 rpm")  # a number before a unit scales it
0.010471975511965978

Units relative to something of the drive take it from :class:`Ratings`: per mille
(``‰``) or per cent of the rated torque or current (CiA 402's torque and current
actual values), and encoder increments for position and speed::

>>> si_factor("torque", "‰", ratings=Ratings(rated_torque=2.4))
0.0024
>>> si_factor("speed", "inc/s", ratings=Ratings(increments_per_rev=4096))  # 2*pi/4096
0.0015339807878856412

A relative unit without its rating is a :class:`~canrls.core.errors.SignalError` naming
the signal and the option that gives the rating (:data:`RATING_OPTIONS`).

A unit that is not listed for the role is a :class:`~canrls.core.errors.SignalError`
naming the message, the signal and the unit, unless the caller gives an
explicit factor (a signal mapping's ``scale``), which then wins over the unit.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

from canrls.core.checks import is_positive
from canrls.core.errors import SignalError

__all__ = ["UNITS", "SI_UNITS", "RELATIVE", "INCREMENTS", "RATING_OPTIONS", "Ratings",
           "si_factor", "axis_of", "known_units", "rating_of"]

_TWO_PI = 2.0 * math.pi
_DEG = math.pi / 180.0

#: Factor to SI per role and unit string (case-sensitive: ``mA`` is not ``MA``).
UNITS: dict[str, dict[str, float]] = {
    "current": {"A": 1.0, "mA": 1e-3, "kA": 1e3},
    "speed": {
        "rad/s": 1.0, "rpm": _TWO_PI / 60.0, "1/min": _TWO_PI / 60.0,
        "rps": _TWO_PI, "deg/s": _DEG,
        "mrad/s": 1e-3,
        "m/s": 1.0, "cm/s": 1e-2, "mm/s": 1e-3, "um/s": 1e-6,
        "m/min": 1.0 / 60.0, "mm/min": 1e-3 / 60.0,
    },
    "position": {
        "rad": 1.0, "mrad": 1e-3, "deg": _DEG, "rev": _TWO_PI,
        "m": 1.0, "cm": 1e-2, "mm": 1e-3, "um": 1e-6,
    },
    "voltage": {"V": 1.0, "mV": 1e-3, "kV": 1e3},
    # the torque (linear axis: force) a drive reports, e.g. CiA 402's torque actual value
    "torque": {"N·m": 1.0, "mN·m": 1e-3, "kN·m": 1e3, "N": 1.0, "mN": 1e-3, "kN": 1e3},
}

#: Units relative to a rating: the fraction of it one unit is (``‰`` of the rated
#: torque for CiA 402's torque actual value 0x6077, of the rated current for the
#: current actual value 0x6078), per role the rating it needs.
RELATIVE: dict[str, float] = {"‰": 1e-3, "%": 1e-2}
_RELATIVE_ROLES: dict[str, str] = {"torque": "rated_torque", "current": "rated_current"}

#: Encoder increments (position) and increments per second (speed): one increment is
#: 1/``increments_per_rev`` of a revolution (linear axis: of a metre).
INCREMENTS: dict[str, dict[str, float]] = {"position": {"inc": 1.0}, "speed": {"inc/s": 1.0}}

#: The option that gives each rating: (command-line flag, ``[signals]`` key, unit).
RATING_OPTIONS: dict[str, tuple[str, str, str]] = {
    "rated_torque": ("--rated-torque", "rated_torque", "N·m; linear axis: N"),
    "rated_current": ("--rated-current", "rated_current", "A"),
    "increments_per_rev": ("--increments-per-rev", "increments_per_rev",
                           "increments per revolution; linear axis: per metre"),
}

#: Other spellings found in DBC files, mapped to the names above.
_ALIASES: dict[str, str] = {
    "r/min": "rpm", "U/min": "rpm", "min^-1": "1/min", "min-1": "1/min",
    "rev/s": "rps", "r/s": "rps", "°/s": "deg/s", "°": "deg", "µm": "um", "μm": "um",
    "rev/min": "rpm", "RPM": "rpm", "µm/s": "um/s", "μm/s": "um/s", "degree": "deg",
    "degrees": "deg", "turn": "rev", "turns": "rev",
    "Nm": "N·m", "N.m": "N·m", "N*m": "N·m", "N m": "N·m", "N-m": "N·m", "mNm": "mN·m",
    "mN.m": "mN·m", "kNm": "kN·m", "kN.m": "kN·m",
    "permille": "‰", "per mille": "‰", "promille": "‰", "o/oo": "‰", "percent": "%",
    "â€°": "‰",  # a DBC saved in UTF-8, read as Windows-1252 (as DBC files are)
    "incr": "inc", "increments": "inc", "increment": "inc", "counts": "inc", "cnt": "inc",
    "ticks": "inc", "incr/s": "inc/s", "increments/s": "inc/s", "counts/s": "inc/s",
    "cnt/s": "inc/s", "ticks/s": "inc/s",
}

#: The SI unit of each role (rotary axis; a linear axis uses m/s, m and N).
SI_UNITS: dict[str, str] = {"current": "A", "speed": "rad/s", "position": "rad", "voltage": "V",
                            "torque": "N·m"}
#: The SI unit of the roles that differ on a linear axis.
_LINEAR_UNITS: dict[str, str] = {"speed": "m/s", "position": "m", "torque": "N"}


def si_unit(role: str, axis: str = "rotary") -> str:
    """The SI unit a role's values are in, on a ``"rotary"`` or ``"linear"`` axis."""
    return _LINEAR_UNITS[role] if axis == "linear" and role in _LINEAR_UNITS else SI_UNITS[role]

#: a unit with a number before it: ``0.1 rpm``, ``0.01deg``
_SCALED = re.compile(r"^(?P<k>[0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*(?P<unit>[^\s0-9.].*)$")


@dataclass(frozen=True)
class Ratings:
    """What a drive's relative units refer to (``None``: not given).

    ``rated_torque`` [N·m] (linear axis: rated force [N]; CiA 402 object 0x6076),
    ``rated_current`` [A] (0x6075), ``increments_per_rev`` (encoder increments per
    revolution; linear axis: per metre). Set with ``--rated-torque``,
    ``--rated-current``, ``--increments-per-rev`` or the same keys of ``[signals]``.
    """

    rated_torque: float | None = None
    rated_current: float | None = None
    increments_per_rev: float | None = None

    def __post_init__(self) -> None:
        for name, (flag, _key, unit) in RATING_OPTIONS.items():
            v = getattr(self, name)
            if v is None:
                continue
            if not is_positive(v):
                raise SignalError(f"{flag} {v!r}: must be a positive number ({unit})")
            object.__setattr__(self, name, float(v))

    def as_dict(self) -> dict[str, float]:
        """The ratings given, ``{key: value}``."""
        return {k: v for k in RATING_OPTIONS if (v := getattr(self, k)) is not None}

    def describe(self, axis: str = "rotary") -> str:
        """The ratings given, in words: ``"rated torque 2.4 N·m, 4096 increments per
        revolution"``."""
        lin = axis == "linear"
        said = []
        if self.rated_torque is not None:
            said.append(f"rated {'force' if lin else 'torque'} {self.rated_torque:g} "
                        f"{'N' if lin else 'N·m'}")
        if self.rated_current is not None:
            said.append(f"rated current {self.rated_current:g} A")
        if self.increments_per_rev is not None:
            said.append(f"{self.increments_per_rev:g} increments per "
                        f"{'metre' if lin else 'revolution'}")
        return ", ".join(said)

_LINEAR = {"m/s", "cm/s", "mm/s", "um/s", "m/min", "mm/min", "m", "cm", "mm", "um"}
_ROTARY = {"rad/s", "mrad/s", "rpm", "1/min", "rps", "deg/s", "rad", "mrad", "deg", "rev"}


def _canonical(unit: str | None) -> str:
    u = (unit or "").strip()
    return _ALIASES.get(u, u)


def known_units(role: str) -> tuple[str, ...]:
    """Unit strings accepted for ``role`` (aliases excluded; the relative ones need a
    rating)."""
    rel = tuple(RELATIVE) if role in _RELATIVE_ROLES else ()
    return tuple(UNITS[role]) + rel + tuple(INCREMENTS.get(role, ()))


def _missing(where: str, unit: str | None, role: str, what: str, rating: str) -> SignalError:
    flag, key, runit = RATING_OPTIONS[rating]
    return SignalError(f"{where}: unit {unit!r} of the {role} signal is {what}: give "
                       f"{flag} VALUE ({runit}) or {key} = VALUE in [signals]")


def si_factor(role: str, unit: str | None, *, message: str | None = None,
              signal: str | None = None, scale: float | None = None,
              ratings: Ratings | None = None, axis: str | None = None) -> float:
    """Factor from the DBC unit ``unit`` of a ``role`` signal to SI.

    Parameters
    ----------
    role : ``"current"``, ``"speed"``, ``"position"``, ``"voltage"`` or ``"torque"``.
    unit : the DBC unit string (``None`` or ``""`` when the DBC gives none); a number
        before it scales it (``"0.1 rpm"``).
    message, signal : named in the error message.
    scale : explicit factor given by the user; returned as is (must be finite, non-zero).
    ratings : what relative units refer to (``‰``, ``%``, ``inc``, ``inc/s``).
    axis : ``"linear"``: an increment is 1/``increments_per_rev`` of a metre (default:
        of a revolution).

    Raises
    ------
    SignalError
        The unit is not known for the role and no ``scale`` was given, or it is
        relative and its rating was not given.
    """
    where = f"{message}.{signal}" if message and signal else (signal or message or role)
    if role not in UNITS:
        raise SignalError(f"unknown signal role {role!r} for {where}; "
                          f"expected one of {', '.join(UNITS)}")
    if scale is not None:
        s = float(scale)
        if not math.isfinite(s) or s == 0.0:
            raise SignalError(f"{where}: explicit scale for {role} must be finite and non-zero, "
                              f"got {scale!r}")
        return s
    u = _canonical(unit)
    if u not in UNITS[role] and u not in RELATIVE and u not in INCREMENTS.get(role, {}):
        m = _SCALED.match(u)
        if m and float(m["k"]) > 0:
            inner = si_factor(role, m["unit"], message=message, signal=signal,
                              ratings=ratings, axis=axis)
            factor = float(m["k"]) * inner
            if not (math.isfinite(factor) and factor != 0.0):  # "1e999 rpm", "1e306 kA"
                raise SignalError(f"{where}: unit {unit!r} of the {role} signal: its number "
                                  f"makes the factor to {SI_UNITS[role]} {factor!r}, not a "
                                  f"finite non-zero number")
            return factor
    r = ratings or Ratings()
    if u in RELATIVE and role in _RELATIVE_ROLES:
        rating = _RELATIVE_ROLES[role]
        v = getattr(r, rating)
        if v is None:
            share = "per mille" if u == "‰" else "per cent"
            raise _missing(where, unit, role, f"{share} of the {rating.replace('_', ' ')}",
                           rating)
        return RELATIVE[u] * v
    if u in INCREMENTS.get(role, {}):
        if r.increments_per_rev is None:
            raise _missing(where, unit, role, "in encoder increments", "increments_per_rev")
        turn = 1.0 if axis == "linear" else _TWO_PI
        return turn / r.increments_per_rev
    try:
        return UNITS[role][u]
    except KeyError:
        raise SignalError(
            f"{where}: unit {unit!r} of the {role} signal cannot be converted to "
            f"{SI_UNITS[role]} (known: {', '.join(known_units(role))}); give an explicit "
            f"scale in the signal mapping") from None


def rating_of(role: str, unit: str | None) -> str | None:
    """The rating (a key of :data:`RATING_OPTIONS`) a ``role`` signal in ``unit``
    refers to, or None for an absolute unit."""
    u = _canonical(unit)
    if (m := _SCALED.match(u)) and u not in UNITS.get(role, {}):
        u = _canonical(m["unit"])
    if u in RELATIVE and role in _RELATIVE_ROLES:
        return _RELATIVE_ROLES[role]
    if u in INCREMENTS.get(role, {}):
        return "increments_per_rev"
    return None


def axis_of(unit: str | None) -> str | None:
    """``"rotary"`` or ``"linear"`` for a speed or position unit, ``None`` otherwise."""
    u = _canonical(unit)
    if (m := _SCALED.match(u)) and u not in _ROTARY | _LINEAR:
        u = _canonical(m["unit"])  # "0.1 rpm"
    if u in _ROTARY:
        return "rotary"
    if u in _LINEAR:
        return "linear"
    return None
