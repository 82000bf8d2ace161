"""The effect library: documentation, names, units, evaluation and residual signatures."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

import canrls
from canrls.core.errors import ConfigError, EffectError, ExpressionError
from canrls.core.samples import Signals
from canrls.estimation.effects import (
    EFFECT_IDS,
    EFFECT_NAMES,
    OPTION_KEYS,
    Cogging,
    Effect,
    Frame,
    effect_spec,
    library,
    parse_effect,
)

ROLES = {"t", "current", "speed", "position", "voltage"}
TERMS = {"drag": {"expr": "omega * abs(omega)", "unit": "rad²/s²"},
         "ripple": {"expr": "sin(6 * theta) * i", "unit": "A", "equation": "mechanical"},
         "rv": {"expr": "i * abs(i)", "unit": "A²", "equation": "electrical"}}
ALL_SPECS = ["inertia", "viscous", "coulomb", "stribeck", "offset", "unbalance", "cogging:24",
             "electrical", "user:drag"]


def _effect(spec: str, **opts: object) -> Effect:
    return parse_effect(spec, {"terms": TERMS, **opts})


def test_every_library_effect_is_documented() -> None:
    classes = library()
    assert tuple(c.NAME for c in classes) == EFFECT_NAMES
    for cls in classes:
        doc = cls.__doc__ or ""
        assert len(doc.strip()) > 40, cls
        assert ".. math::" in doc, cls
        assert cls.EQUATION_TEXT, cls
        assert len(cls.RESIDUAL_SIGNATURE) > 20, cls
        # what a change of it means on a drive in service, and what to check (the
        # fleet's alerts say these)
        assert all(len(c) > 10 for c in cls.CHANGE_CAUSE) and len(cls.CHANGE_CHECK) > 10, cls
        assert cls.EQUATION in ("mechanical", "electrical"), cls
        assert cls.REQUIRES <= ROLES, cls
        assert cls.COMPONENTS, cls
        for comp in cls.COMPONENTS:
            assert comp.description and comp.linear_description, (cls, comp)
            for axis in ("rotary", "linear"):
                for kt_known in (True, False):
                    unit = comp.units.get(axis, kt_known)  # type: ignore[arg-type]
                    assert unit and unit.strip() == unit, (cls, comp, axis, kt_known)
        text = cls.describe()
        assert cls.RESIDUAL_SIGNATURE in text and cls.NAME in text


def test_effect_ids_match_the_shipped_dbc() -> None:
    dbc = (Path(canrls.__file__).parent / "data" / "canrls.dbc").read_text()
    line = next(ln for ln in dbc.splitlines() if ln.startswith("VAL_ 771 EffectId"))
    pairs = dict((name, int(num)) for num, name in re.findall(r'(\d+) "(\w+)"', line))
    pairs.pop("none")
    assert pairs == dict(EFFECT_IDS)
    assert EFFECT_IDS == {"inertia": 1, "viscous": 2, "coulomb": 3, "stribeck": 4, "offset": 5,
                          "unbalance": 6, "cogging": 7, "electrical": 8, "user": 9}


def test_parameter_names_follow_the_architecture() -> None:
    names = [p.name for s in ALL_SPECS for p in _effect(s).parameters()]
    assert names == ["inertia.J", "viscous.B", "coulomb.Tc", "stribeck.Ts", "offset.T0",
                     "unbalance.sin", "unbalance.cos", "cogging:24.sin", "cogging:24.cos",
                     "electrical.R", "electrical.L", "electrical.Ke", "user:drag.c"]


@pytest.mark.parametrize(("spec", "axis", "kt_known", "units"), [
    ("inertia", "rotary", True, ["kg·m²"]),
    ("inertia", "linear", True, ["kg"]),
    ("inertia", "rotary", False, ["A·s²/rad"]),
    ("inertia", "linear", False, ["A·s²/m"]),
    ("viscous", "rotary", True, ["N·m·s/rad"]),
    ("viscous", "linear", True, ["N·s/m"]),
    ("viscous", "rotary", False, ["A·s/rad"]),
    ("coulomb", "linear", True, ["N"]),
    ("coulomb", "rotary", False, ["A"]),
    ("cogging:3", "rotary", True, ["N·m", "N·m"]),
    ("unbalance", "linear", False, ["A", "A"]),
    ("electrical", "rotary", True, ["Ohm", "H", "V·s/rad"]),
    ("electrical", "linear", False, ["Ohm", "H", "V·s/m"]),
    ("user:drag", "rotary", True, ["N·m/(rad²/s²)"]),
    ("user:ripple", "linear", False, ["A/A"]),
    ("user:rv", "rotary", False, ["V/A²"]),
])
def test_units_per_axis_and_target(spec: str, axis: str, kt_known: bool,
                                   units: list[str]) -> None:
    eff = _effect(spec, axis=axis)
    assert [p.unit for p in eff.parameters(kt_known=kt_known)] == units


def test_parse_names_ids_orders_and_equations() -> None:
    cog = parse_effect(" Cogging:24 ")
    assert isinstance(cog, Cogging)
    assert (cog.name, cog.order, cog.effect_id, cog.equation) == ("cogging:24", 24, 7,
                                                                   "mechanical")
    assert [p.component for p in cog.parameters()] == [0, 1]
    assert {p.order for p in cog.parameters()} == {24}
    assert parse_effect("unbalance").order == 1
    assert parse_effect("electrical").equation == "electrical"
    assert parse_effect("electrical").parameters()[0].equation_index == 1
    assert _effect("user:rv").equation == "electrical"
    assert _effect("user:ripple").requires == {"current", "position"}
    assert parse_effect("offset").requires == frozenset()
    assert parse_effect("cogging:2") == parse_effect("cogging:2")
    assert parse_effect("cogging:2") != parse_effect("cogging:3")
    assert parse_effect("coulomb", {"band": 0.1}) != parse_effect("coulomb")
    assert len({parse_effect("viscous"), parse_effect("viscous")}) == 1
    assert "Coulomb('coulomb'" in repr(parse_effect("coulomb"))
    assert effect_spec(7, 24) == "cogging:24" and effect_spec(1) == "inertia"


@pytest.mark.parametrize(("spec", "opts", "fragments"), [
    ("friction", {}, ["'friction'", "inertia", "cogging:K", "user:NAME"]),
    ("cogging", {}, ["'cogging'", "cogging:K"]),
    ("cogging:", {}, ["cogging:K"]),
    ("cogging:0", {}, ["'0'", "from 1 to 65535"]),
    ("cogging:-3", {}, ["'-3'"]),
    ("cogging:2.5", {}, ["'2.5'"]),
    ("inertia:2", {}, ["'inertia'", "no argument"]),
    ("user", {}, ["user:NAME"]),
    ("user:wind", {"terms": TERMS}, ["'wind'", "drag", "ripple"]),
    ("user:wind", {}, ["'wind'", "none"]),
    ("coulomb", {"band": 0.0}, ["band", "0.0"]),
    ("coulomb", {"band": -1}, ["band", "-1"]),
    ("stribeck", {"speed": "fast"}, ["speed", "'fast'"]),
    ("stribeck", {"band": float("inf")}, ["band", "inf"]),
    ("unbalance", {"pitch": 0}, ["pitch", "0"]),
    ("inertia", {"axis": "planar"}, ["axis", "'planar'"]),
    ("inertia", {"bandwidth": 1}, ["bandwidth"]),
    ("user:bad", {"terms": {"bad": {"expr": "1", "colour": "red"}}}, ["colour"]),
    ("user:bad", {"terms": {"bad": {"unit": "1"}}}, ["expr"]),
    ("user:bad", {"terms": {"bad": {"expr": "1", "equation": "thermal"}}}, ["'thermal'"]),
    ("user:bad", {"terms": {"bad": {"expr": "1", "range": [2, 1]}}}, ["range"]),
])
def test_unknown_effects_and_bad_parameters_raise_effect_error(
        spec: str, opts: dict, fragments: list[str]) -> None:
    with pytest.raises(EffectError) as info:
        parse_effect(spec, opts)
    for f in fragments:
        assert f in str(info.value)
    assert isinstance(info.value, ConfigError)
    with pytest.raises(EffectError, match="id 9"):
        effect_spec(9)
    with pytest.raises(EffectError, match="42"):
        effect_spec(42)


def test_bad_user_expression_raises_expression_error_naming_the_term() -> None:
    with pytest.raises(ExpressionError, match=r"'gust'.*'os.system'"):
        parse_effect("user:gust", {"terms": {"gust": {"expr": "os.system('x')"}}})
    assert set(OPTION_KEYS) == {"axis", "pitch", "band", "speed", "terms"}


# ----------------------------------------------------------------------- evaluation
T = np.arange(4000) * 1e-3
W = 3.0 * np.sin(2 * np.pi * 0.5 * T)
WD = 3.0 * np.pi * np.cos(2 * np.pi * 0.5 * T)
TH = 1.0 + 3.0 / np.pi * (1 - np.cos(2 * np.pi * 0.5 * T))
CUR = 2.0 * np.cos(2 * np.pi * 3 * T)
ID = -12.0 * np.pi * np.sin(2 * np.pi * 3 * T)
U = np.linspace(-5, 5, len(T))
SIG = Signals(T, CUR, W, TH, U)


@pytest.mark.parametrize(("spec", "params", "expected"), [
    ("inertia", {"inertia.J": 0.01}, 0.01 * WD),
    ("viscous", {"B": 0.2}, 0.2 * W),
    ("coulomb", {"coulomb.Tc": 0.3}, 0.3 * np.tanh(W / 0.01)),
    ("stribeck", {"stribeck.Ts": 0.1}, 0.1 * np.tanh(W / 0.01) * np.exp(-W**2)),
    ("offset", {"offset.T0": -0.05}, np.full(len(T), -0.05)),
    ("unbalance", {"unbalance.sin": 0.2, "unbalance.cos": -0.1},
     0.2 * np.sin(TH) - 0.1 * np.cos(TH)),
    ("cogging:12", {"cogging:12.sin": 0.01, "cogging:12.cos": 0.02},
     0.01 * np.sin(12 * TH) + 0.02 * np.cos(12 * TH)),
    ("electrical", {"electrical.R": 0.5, "electrical.L": 1e-3, "electrical.Ke": 0.1},
     0.5 * CUR + 1e-3 * ID + 0.1 * W),
    ("user:drag", {"user:drag.c": 0.02}, 0.02 * W * np.abs(W)),
])
def test_evaluate_follows_the_conventions(spec: str, params: dict,
                                          expected: np.ndarray) -> None:
    out = _effect(spec).evaluate(params, SIG)
    np.testing.assert_allclose(out[5:-5], expected[5:-5], rtol=1e-4, atol=1e-5)


def test_linear_axis_angle_uses_the_pitch() -> None:
    pitch = 0.02
    x = np.linspace(-0.3, 0.5, 1000)
    s = Signals(np.arange(1000) * 1e-3, np.zeros(1000), np.zeros(1000), x)
    cog = parse_effect("cogging:3", {"axis": "linear", "pitch": pitch})
    out = cog.evaluate({"cogging:3.sin": 1.0, "cogging:3.cos": 0.5}, s)
    ang = 2 * np.pi * x / pitch
    np.testing.assert_allclose(out, np.sin(3 * ang) + 0.5 * np.cos(3 * ang), atol=1e-12)
    assert cog.parameters()[0].description.startswith("cogging force")
    with pytest.raises(EffectError, match=r"cogging:3\.cos"):
        cog.evaluate({"cogging:3.sin": 1.0}, s)


def test_missing_signal_in_evaluate_is_named() -> None:
    s = Signals(T, CUR, W)
    with pytest.raises(EffectError, match="'position'"):
        parse_effect("unbalance").evaluate({"sin": 1, "cos": 1}, s)
    frame = Frame.from_signals(s)
    with pytest.raises(EffectError, match="'voltage'"):
        frame.get("voltage")


# ----------------------------------------------------------------- residual signatures
def _sweep(n: int = 2001) -> np.ndarray:
    return np.linspace(-5.0, 5.0, n)


def test_signature_coulomb_is_a_signed_step_at_zero_speed() -> None:
    w = _sweep()
    r = parse_effect("coulomb").evaluate({"Tc": 1.0}, Frame(w * 0, w * 0, w))
    assert np.allclose(r[w < -0.1], -1.0) and np.allclose(r[w > 0.1], 1.0)


def test_signature_viscous_is_linear_and_odd() -> None:
    w = _sweep()
    r = parse_effect("viscous").evaluate({"B": 2.0}, Frame(w * 0, w * 0, w))
    np.testing.assert_allclose(r, -r[::-1])
    assert np.polyfit(w, r, 1)[0] == pytest.approx(2.0)


def test_signature_stribeck_is_a_bump_decaying_with_speed() -> None:
    w = _sweep()
    r = parse_effect("stribeck").evaluate({"Ts": 1.0}, Frame(w * 0, w * 0, w))
    pos = r[w > 0.05]
    assert np.all(np.diff(pos) < 0) and pos[-1] < 1e-9 and pos[0] > 0.9
    np.testing.assert_allclose(r, -r[::-1])


def test_signature_offset_is_a_constant_mean() -> None:
    w = _sweep()
    r = parse_effect("offset").evaluate({"T0": 0.7}, Frame(w * 0, w * 0, w))
    assert np.all(r == 0.7)


@pytest.mark.parametrize(("spec", "order"), [("unbalance", 1), ("cogging:7", 7),
                                             ("cogging:24", 24)])
def test_signature_periodic_terms_peak_at_their_rotation_order(spec: str, order: int) -> None:
    n = 4096
    theta = np.arange(n) * 2 * np.pi * 8 / n  # 8 revolutions, uniformly sampled
    frame = Frame(theta * 0, theta * 0, theta * 0 + 1, position=theta, angle=theta)
    r = parse_effect(spec).evaluate({"sin": 0.3, "cos": 0.4}, frame)
    spectrum = np.abs(np.fft.rfft(r))
    orders = np.arange(len(spectrum)) / 8
    assert orders[np.argmax(spectrum)] == order


def test_signature_inertia_correlates_with_acceleration() -> None:
    r = parse_effect("inertia").evaluate({"J": 0.5}, SIG)
    assert np.corrcoef(r, WD)[0, 1] > 0.9999
    assert abs(np.corrcoef(r, W)[0, 1]) < 0.05


def test_docs_page_lists_every_effect_signature_and_unit() -> None:
    doc = (Path(__file__).resolve().parents[2] / "docs" / "effects.md").read_text()
    for cls in library():
        assert f"`{cls.NAME}" in doc, cls.NAME
        for comp in cls.COMPONENTS:
            if cls.NAME != "user":
                assert comp.units.rotary in doc and comp.units.linear in doc, comp
    for spec in ALL_SPECS:
        for p in _effect(spec).parameters():
            if not spec.startswith("user"):
                assert p.name.replace("24", "K") in doc or p.name in doc, p.name
