"""Conversion of DBC unit strings to SI, per signal role.

A DBC states the physical unit of each signal as free text (``"A"``, ``"rpm"``,
``"deg"``...). canrls works in SI (:mod:`canrls.signals`): current in A, speed in
rad/s (linear axis: m/s), position in rad (linear axis: m), voltage in V. This
module maps a unit string to the factor that turns a DBC physical value into SI::

    value_SI = factor * value_DBC

>>> si_factor("speed", "rpm")  # 2*pi/60
0.10471975511965977
>>> si_factor("current", "mA")
0.001

A unit that is not listed for the role is a :class:`~canrls.errors.SignalError`
naming the message, the signal and the unit, unless the caller gives an
explicit factor (a signal mapping's ``scale``), which then wins over the unit.
"""

from __future__ import annotations

import math

from canrls.errors import SignalError

__all__ = ["UNITS", "SI_UNITS", "si_factor", "axis_of", "known_units"]

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
}

#: Other spellings found in DBC files, mapped to the names above.
_ALIASES: dict[str, str] = {
    "r/min": "rpm", "U/min": "rpm", "min^-1": "1/min", "min-1": "1/min",
    "rev/s": "rps", "r/s": "rps", "°/s": "deg/s", "°": "deg", "µm": "um", "μm": "um",
    "rev/min": "rpm", "RPM": "rpm", "µm/s": "um/s", "μm/s": "um/s", "degree": "deg",
    "degrees": "deg", "turn": "rev", "turns": "rev",
}

#: The SI unit of each role (rotary axis; a linear axis uses m/s and m).
SI_UNITS: dict[str, str] = {"current": "A", "speed": "rad/s", "position": "rad", "voltage": "V"}

_LINEAR = {"m/s", "cm/s", "mm/s", "um/s", "m/min", "mm/min", "m", "cm", "mm", "um"}
_ROTARY = {"rad/s", "mrad/s", "rpm", "1/min", "rps", "deg/s", "rad", "mrad", "deg", "rev"}


def _canonical(unit: str | None) -> str:
    u = (unit or "").strip()
    return _ALIASES.get(u, u)


def known_units(role: str) -> tuple[str, ...]:
    """Unit strings accepted for ``role`` (aliases excluded)."""
    return tuple(UNITS[role])


def si_factor(role: str, unit: str | None, *, message: str | None = None,
              signal: str | None = None, scale: float | None = None) -> float:
    """Factor from the DBC unit ``unit`` of a ``role`` signal to SI.

    Parameters
    ----------
    role : ``"current"``, ``"speed"``, ``"position"`` or ``"voltage"``.
    unit : the DBC unit string (``None`` or ``""`` when the DBC gives none).
    message, signal : named in the error message.
    scale : explicit factor given by the user; returned as is (must be finite, non-zero).

    Raises
    ------
    SignalError
        The unit is not known for the role and no ``scale`` was given.
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
    try:
        return UNITS[role][u]
    except KeyError:
        raise SignalError(
            f"{where}: unit {unit!r} of the {role} signal cannot be converted to "
            f"{SI_UNITS[role]} (known: {', '.join(UNITS[role])}); give an explicit "
            f"scale in the signal mapping") from None


def axis_of(unit: str | None) -> str | None:
    """``"rotary"`` or ``"linear"`` for a speed or position unit, ``None`` otherwise."""
    u = _canonical(unit)
    if u in _ROTARY:
        return "rotary"
    if u in _LINEAR:
        return "linear"
    return None
