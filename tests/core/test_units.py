"""canrls.core.units: DBC unit strings -> SI factors, per role."""

from __future__ import annotations

import doctest
import math

import pytest

import canrls.can.estimator_frames
import canrls.can.protocol
import canrls.core.effect_names
import canrls.core.units
import canrls.processor.pairing
from canrls.core.errors import ConfigError, SignalError
from canrls.core.units import (
    RATING_OPTIONS,
    SI_UNITS,
    UNITS,
    Ratings,
    axis_of,
    known_units,
    rating_of,
    si_factor,
)


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


@pytest.mark.parametrize("role, unit", [("speed", "1e999 rpm"), ("current", "1e306 kA"),
                                        ("position", "1e-323 mrad")])
def test_a_scaled_unit_whose_factor_is_not_a_number_names_the_signal(role: str,
                                                                     unit: str) -> None:
    """A DBC unit "1e999 rpm" made the factor infinite: the error came later, blaming
    "<defaults>: model.ranges.speed = -inf" instead of the signal and its unit."""
    with pytest.raises(SignalError, match=rf"Fb\.Sig: unit {unit!r} of the {role} signal: "
                                          rf"its number makes the factor"):
        si_factor(role, unit, message="Fb", signal="Sig")


def test_unknown_role() -> None:
    with pytest.raises(SignalError, match="unknown signal role 'pressure'"):
        si_factor("pressure", "bar")


@pytest.mark.parametrize("role, unit, factor", [
    ("torque", "N·m", 1.0), ("torque", "Nm", 1.0), ("torque", "N.m", 1.0),
    ("torque", "mNm", 1e-3), ("torque", "N", 1.0), ("torque", "kN", 1e3),
    # a number before the unit scales it (as a DBC writes "0.1 rpm" for a factor of 1)
    ("speed", "0.1 rpm", 0.1 * 2 * math.pi / 60), ("speed", "0.1rpm", 0.1 * 2 * math.pi / 60),
    ("position", "0.01 deg", 1e-2 * math.pi / 180), ("current", "10 mA", 1e-2),
    # relative to the ratings: per mille / per cent of the rated torque or current
    ("torque", "‰", 2.4e-3), ("torque", "permille", 2.4e-3), ("torque", "%", 2.4e-2),
    ("torque", "0.1 %", 2.4e-3), ("current", "‰", 5e-3), ("current", "per mille", 5e-3),
    ("torque", "‰".encode().decode("cp1252"), 2.4e-3),  # a UTF-8 DBC read as cp1252
    # encoder increments: 1/4096 of a revolution
    ("position", "inc", 2 * math.pi / 4096), ("position", "counts", 2 * math.pi / 4096),
    ("speed", "inc/s", 2 * math.pi / 4096), ("speed", "increments/s", 2 * math.pi / 4096),
])
def test_torque_scaled_and_relative_units(role: str, unit: str, factor: float) -> None:
    r = Ratings(rated_torque=2.4, rated_current=5.0, increments_per_rev=4096)
    assert si_factor(role, unit, ratings=r) == pytest.approx(factor, rel=1e-14)


def test_increments_on_a_linear_axis_are_per_metre() -> None:
    r = Ratings(increments_per_rev=1e6)
    assert si_factor("position", "inc", ratings=r, axis="linear") == pytest.approx(1e-6)
    assert si_factor("speed", "inc/s", ratings=r, axis="linear") == pytest.approx(1e-6)
    assert axis_of("inc") is None and axis_of("0.1 rpm") == "rotary"


@pytest.mark.parametrize("role, unit, flag, what", [
    ("torque", "‰", "--rated-torque", "per mille of the rated torque"),
    ("torque", "%", "--rated-torque", "per cent of the rated torque"),
    ("current", "‰", "--rated-current", "per mille of the rated current"),
    ("position", "inc", "--increments-per-rev", "in encoder increments"),
    ("speed", "inc/s", "--increments-per-rev", "in encoder increments"),
])
def test_a_relative_unit_without_its_rating_names_signal_and_flag(
        role: str, unit: str, flag: str, what: str) -> None:
    with pytest.raises(SignalError) as e:
        si_factor(role, unit, message="TPDO1", signal="Sig")
    msg = str(e.value)
    assert msg.startswith(f"TPDO1.Sig: unit {unit!r} of the {role} signal is {what}: "
                          f"give {flag} VALUE"), msg
    assert RATING_OPTIONS[rating_of(role, unit)][1] + " = VALUE in [signals]" in msg


def test_ratings_must_be_positive_and_name_their_flag() -> None:
    assert Ratings(rated_torque=3).as_dict() == {"rated_torque": 3.0}
    assert Ratings(rated_torque=2.4, increments_per_rev=4096).describe() == \
        "rated torque 2.4 N·m, 4096 increments per revolution"
    assert Ratings(rated_torque=20).describe("linear") == "rated force 20 N"
    for bad in (0, -1.0, math.nan, math.inf, True):
        with pytest.raises(SignalError, match="--rated-torque .*: must be a positive number"):
            Ratings(rated_torque=bad)
    assert rating_of("voltage", "%") is None and rating_of("torque", "N·m") is None


def test_axis() -> None:
    assert axis_of("rpm") == axis_of("deg") == axis_of("rad/s") == "rotary"
    assert axis_of("mm/s") == axis_of("um") == axis_of("m") == "linear"
    assert axis_of("A") is None and axis_of(None) is None


@pytest.mark.parametrize("module", [canrls.core.units, canrls.can.protocol,
                                    canrls.processor.pairing, canrls.can.estimator_frames,
                                    canrls.core.effect_names])
def test_doctests(module) -> None:
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS)
    assert result.failed == 0
