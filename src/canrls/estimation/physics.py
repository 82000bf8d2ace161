"""Physics that cannot be: estimates no drive can have, and their likely cause.

A negative inertia, friction that pushes the motor, a negative resistance: a fit may
still match the data well with them (a flipped sign of the current flips every
parameter), so the estimate is checked against what physics allows and each finding
names its likely cause. Used by ``canrls fit``, ``diagnose``, ``validate``, the report
and the daemon's health frame (``Implausible``).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any, Protocol

from canrls.core.checks import is_positive

__all__ = ["Implausible", "SIGMAS", "check_physics", "describe"]

#: A parameter that must not be negative is flagged when it is below zero by more than
#: this many standard deviations (a small negative value within its sigma is noise).
SIGMAS = 3.0

#: Back-EMF constant against the configured torque constant: a permanent-magnet motor's
#: Kt / Ke lies near 1 (1.5 with an amplitude-invariant dq transform, others by line
#: and phase conventions); beyond this factor either way one of them is in another unit.
KT_KE_FACTOR = 3.0

# what must be > 0 (J, R, L) and what must not be negative beyond SIGMAS (friction, Ke)
_POSITIVE = ("inertia.J", "electrical.R", "electrical.L")
_NOT_NEGATIVE = ("viscous.B", "coulomb.Tc", "electrical.Ke")

_SIGN = ("the output's sign is opposite to the speed's: flip the sign of the current "
         "(or torque) signal with --signal current=MESSAGE.SIGNAL:-1, or of the speed")


class _Estimate(Protocol):
    """A parameter as :func:`check_physics` reads it (read only: result objects are
    frozen)."""

    @property
    def name(self) -> str: ...
    @property
    def value(self) -> float: ...
    @property
    def sigma(self) -> float: ...
    @property
    def identifiable(self) -> bool: ...


@dataclass(frozen=True)
class Implausible:
    """One parameter no drive can have, the rule it breaks and the likely cause."""

    parameter: str
    value: float
    sigma: float
    rule: str
    cause: str

    def to_dict(self) -> dict[str, Any]:
        return {"parameter": self.parameter, "value": self.value, "sigma": self.sigma,
                "rule": self.rule, "cause": self.cause}

    def format(self) -> str:
        return f"{self.parameter} = {self.value:.6g} ± {self.sigma:.3g} ({self.rule})"


def describe(found: Iterable[Implausible]) -> list[str]:
    """One line per likely cause, naming the parameters it explains."""
    causes: dict[str, list[Implausible]] = {}
    for i in found:
        causes.setdefault(i.cause, []).append(i)
    return [f"PHYSICS THAT CANNOT BE: {'; '.join(i.format() for i in items)}; likely {cause}"
            for cause, items in causes.items()]


def check_physics(params: Iterable[_Estimate], kt: float | None = None
                  ) -> tuple[Implausible, ...]:
    """The parameters of ``params`` that physics rules out (identifiable ones only: a
    parameter the data cannot tell is the prior's and says nothing), with ``kt`` the
    configured torque constant (checked against a back-EMF constant when one was
    identified)."""
    by = {p.name: p for p in params if p.identifiable and math.isfinite(p.value)}
    bad: dict[str, str] = {}
    for name in _POSITIVE:
        p = by.get(name)
        if p is not None and not p.value > 0.0:
            bad[name] = "not positive"
    for name in _NOT_NEGATIVE:
        p = by.get(name)
        if p is not None and p.value < -SIGMAS * _sd(p.sigma):
            bad[name] = (f"negative by {-p.value / _sd(p.sigma):.3g} sigma"
                         if _sd(p.sigma) > 0 else "negative")
    mech = [n for n in ("inertia.J", "viscous.B", "coulomb.Tc") if n in by]
    flipped = len(mech) >= 2 and all(n in bad for n in mech)
    out = [Implausible(n, by[n].value, by[n].sigma, rule, _SIGN if flipped and n in mech
                       else _cause(n)) for n, rule in bad.items()]
    ke = by.get("electrical.Ke")
    if kt is not None and ke is not None and ke.value > 0.0 and kt > 0.0:
        ratio = kt / ke.value
        if not 1.0 / KT_KE_FACTOR <= ratio <= KT_KE_FACTOR:
            out.append(Implausible(
                "kt", kt, 0.0,
                f"the torque constant is {ratio:.3g} times the back-EMF constant "
                f"Ke = {ke.value:.4g} V·s/rad the data show (about 1 to 1.5 for a "
                f"permanent-magnet motor)",
                "a wrong --kt, or the current or voltage in another unit than the DBC "
                "says (mA read as A, a per-unit value)"))
    return tuple(out)


def _sd(sigma: float) -> float:
    return sigma if is_positive(sigma) else 0.0


_CAUSES: Mapping[str, str] = {
    "inertia.J": ("a delay between the current and the speed the model does not know (the "
                  "current lags), the speed in another unit or time base than the DBC "
                  "says, or too little acceleration in the data"),
    "viscous.B": ("an effect the model lacks that grows with speed the other way (Stribeck "
                  "friction, a load), or the speed in another unit than the DBC says"),
    "coulomb.Tc": ("an offset or a load the model lacks (the speed mostly one way: record "
                   "both directions), or the sign of the current or speed"),
    "electrical.R": "the sign or the unit of the current or the voltage",
    "electrical.L": "a delay between current and voltage, or the sign of the voltage",
    "electrical.Ke": "the sign of the speed or of the voltage",
}


def _cause(name: str) -> str:
    return _CAUSES.get(name, "the sign or unit of a signal")
