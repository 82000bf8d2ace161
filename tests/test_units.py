"""canrls.can.units: DBC unit strings -> SI factors, per role."""

from __future__ import annotations

import doctest
import math

import pytest

import canrls.can.frames
import canrls.can.pairing
import canrls.can.protocol
import canrls.can.units
import canrls.effect_names
from canrls.can.units import SI_UNITS, UNITS, axis_of, known_units, si_factor
from canrls.errors import ConfigError, SignalError


@pytest.mark.parametrize("role, unit, factor", [
    ("current", "A", 1.0), ("current", "mA", 1e-3), ("current", "kA", 1e3),
    ("speed", "rad/s", 1.0), ("speed", "rpm", 2 * math.pi / 60),
    ("speed", "1/min", 2 * math.pi / 60), ("speed", "rps", 2 * math.pi),
    ("speed", "deg/s", math.pi / 180), ("speed", "m/s", 1.0), ("speed", "mm/s", 1e-3),
    ("position", "rad", 1.0), ("position", "deg", math.pi / 180), ("position", "rev", 2 * math.pi),
    ("position", "m", 1.0), ("position", "mm", 1e-3), ("position", "um", 1e-6),
    ("voltage", "V", 1.0), ("voltage", "mV", 1e-3), ("voltage", "kV", 1e3),
    # other spellings
    ("speed", "r/min", 2 * math.pi / 60), ("speed", "U/min", 2 * math.pi / 60),
    ("position", "°", math.pi / 180), ("position", "µm", 1e-6),
    ("speed", " rpm ", 2 * math.pi / 60),
])
def test_factors(role: str, unit: str, factor: float) -> None:
    assert si_factor(role, unit) == pytest.approx(factor, rel=1e-15)


def test_every_role_has_its_si_unit_with_factor_one() -> None:
    for role, unit in SI_UNITS.items():
        assert si_factor(role, unit) == 1.0
        assert unit in known_units(role)
    assert set(UNITS) == set(SI_UNITS)


@pytest.mark.parametrize("role, unit", [
    ("current", "MA"), ("current", ""), ("current", None), ("speed", "rad"), ("position", "rpm"),
    ("voltage", "A"), ("speed", "degC"),
])
def test_unknown_unit_names_message_signal_and_unit(role: str, unit: str | None) -> None:
    with pytest.raises(SignalError, match=rf"Fb\.Sig: unit {unit!r} of the {role} signal cannot "
                                          rf"be converted to {SI_UNITS[role]}") as e:
        si_factor(role, unit, message="Fb", signal="Sig")
    assert isinstance(e.value, ConfigError) and isinstance(e.value, ValueError)
    assert "explicit scale" in str(e.value)


def test_explicit_scale_wins() -> None:
    assert si_factor("current", "weird", scale=0.5) == 0.5
    assert si_factor("speed", None, scale=-2) == -2.0
    for bad in (0, math.nan, math.inf):
        with pytest.raises(SignalError, match="explicit scale"):
            si_factor("speed", "rpm", scale=bad, message="M", signal="S")


def test_unknown_role() -> None:
    with pytest.raises(SignalError, match="unknown signal role 'torque'"):
        si_factor("torque", "N.m")


def test_axis() -> None:
    assert axis_of("rpm") == axis_of("deg") == axis_of("rad/s") == "rotary"
    assert axis_of("mm/s") == axis_of("um") == axis_of("m") == "linear"
    assert axis_of("A") is None and axis_of(None) is None


@pytest.mark.parametrize("module", [canrls.can.units, canrls.can.protocol, canrls.can.pairing,
                                    canrls.can.frames, canrls.effect_names])
def test_doctests(module) -> None:
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS)
    assert result.failed == 0
