"""canrls.core.effect_names: the one table of effect ids and the one grammar of effect names,
shared by the bus commands (canrls.can.estimator_frames) and the effect library."""

from __future__ import annotations

from pathlib import Path

import pytest

from canrls.can import estimator_frames as frames
from canrls.core.effect_names import EffectId, EffectName, EquationId, parse_effect_name
from canrls.core.errors import CommandError, ConfigError, EffectError
from canrls.estimation import effects
from canrls.estimation.model import Model
from canrls.processor.config import load_model, read_toml


def test_one_effect_table() -> None:
    assert frames.EffectId is EffectId and frames.EquationId is EquationId
    assert {c.NAME: c.EFFECT_ID for c in effects.library()} == {
        e.effect_name: e for e in EffectId if e}
    assert all(type(c.EFFECT_ID) is EffectId for c in effects.library())
    # the bus names components as the library does
    assert {EffectId(c.EFFECT_ID): tuple(k.symbol for k in c.COMPONENTS)
            for c in effects.library()} == frames.COMPONENTS


def test_equation_ids() -> None:
    assert [(e.label, int(e)) for e in EquationId] == [("mechanical", 0), ("electrical", 1)]
    assert EquationId.from_label("electrical") is EquationId.ELECTRICAL
    with pytest.raises(EffectError, match="'thermal'"):
        EquationId.from_label("thermal")
    m = Model(["inertia", "electrical"])
    assert [(eq.name, eq.index) for eq in m.equations] == [
        ("mechanical", EquationId.MECHANICAL), ("electrical", EquationId.ELECTRICAL)]
    assert m.equations[1].parameters[0].equation_index is EquationId.ELECTRICAL


@pytest.mark.parametrize(("spec", "user", "want"), [
    ("viscous", "name", EffectName(EffectId.VISCOUS)),
    (" Cogging : 24 ", "name", EffectName(EffectId.COGGING, order=24)),
    ("user:drag", "name", EffectName(EffectId.USER, term="drag")),
    ("user:3", "index", EffectName(EffectId.USER, order=3)),
    ("cogging:7", "index", EffectName(EffectId.COGGING, order=7)),
])
def test_grammar(spec: str, user: str, want: EffectName) -> None:
    got = parse_effect_name(spec, user=user)  # type: ignore[arg-type]
    assert got == want
    assert parse_effect_name(str(got), user=user) == got  # type: ignore[arg-type]


@pytest.mark.parametrize(("spec", "user", "fragments", "result"), [
    ("gravity", "name", ["'gravity'", "valid effects", "cogging:K"], "UNKNOWN_EFFECT"),
    ("none", "name", ["'none'"], "UNKNOWN_EFFECT"),
    ("cogging", "name", ["cogging:K", "e.g. cogging:24"], "BAD_VALUE"),
    ("cogging:0", "name", ["'0'", "from 1 to 65535"], "BAD_VALUE"),
    # 5,000 digits: Python's int() refused them (exit 3); the message names 20 of them
    ("cogging:" + "9" * 5000, "name", ["from 1 to 65535", "(5000 characters)"], "BAD_VALUE"),
    ("cogging:²", "name", ["'²'"], "BAD_VALUE"),
    ("user", "name", ["user:NAME"], "BAD_VALUE"),
    ("user:drag", "index", ["'drag'", "user:N"], "BAD_VALUE"),
    ("inertia:2", "name", ["'inertia'", "no argument"], "BAD_VALUE"),
])
def test_both_parsers_give_the_same_errors(spec: str, user: str, fragments: list[str],
                                           result: str) -> None:
    with pytest.raises(EffectError) as info:
        parse_effect_name(spec, user=user)  # type: ignore[arg-type]
    for f in fragments:
        assert f in str(info.value)
    if user == "name":  # the configuration's parser
        with pytest.raises(EffectError) as lib:
            effects.parse_effect(spec)
        assert str(lib.value) == str(info.value)
    if spec != "user:drag" or user == "index":  # the bus commands' parser
        with pytest.raises(frames.CommandFrameError) as cmd:
            frames.parse_effect(spec)
        assert cmd.value.result is frames.CommandResult[result]


def test_the_bus_parser_checks_the_order_field() -> None:
    assert frames.parse_effect("cogging:65535") == (EffectId.COGGING, 65535)
    assert frames.parse_effect("user:2") == (EffectId.USER, 2)
    with pytest.raises(CommandError, match="16-bit"):
        frames.parse_effect("cogging:65536")


def test_read_toml_names_file_and_key(tmp_path: Path) -> None:
    good = tmp_path / "drive.toml"
    good.write_text('[model]\neffects = ["inertia"]\n[can]\nperiod = 0.001\n')
    assert read_toml(good) == {"model": {"effects": ["inertia"]}, "can": {"period": 0.001}}
    assert read_toml(good, "model") == {"effects": ["inertia"]}
    assert load_model(good).effect_names == Model(["inertia"]).effect_names == ("inertia",)
    bad = tmp_path / "broken.toml"
    bad.write_text("[model\n")
    cases = [
        (lambda: read_toml(bad), r"^.*broken\.toml: invalid TOML: .*line 1"),
        (lambda: read_toml(bad, key="daemon.model_file"),
         r"^daemon\.model_file = .*broken\.toml: invalid TOML"),
        (lambda: read_toml(tmp_path / "missing.toml", "model"), r"missing\.toml: cannot read"),
        (lambda: read_toml(good, "daemon", key="daemon.model_file"),
         r"^daemon\.model_file = .*drive\.toml: no \[daemon\] table$"),
        (lambda: load_model(bad), r"broken\.toml: invalid TOML"),
    ]
    for call, pattern in cases:
        with pytest.raises(ConfigError, match=pattern):
            call()
    latin = tmp_path / "latin.toml"
    latin.write_bytes(b'[model]\neffects = ["in\xe9rtia"]\n')
    with pytest.raises(ConfigError, match=r"latin\.toml: invalid TOML"):
        read_toml(latin)
