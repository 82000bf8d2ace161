"""Several drives on one bus: the ID rules, ``[[axes]]`` and ``--axes``, and the bad
input of a machine's configuration (one ``error:`` line each, before anything starts)."""

from __future__ import annotations

from pathlib import Path

import pytest
from cli_tool import cli_error

from canrls.can.idrules import IdRule, parse_rule, parse_rules
from canrls.core.errors import ConfigError
from canrls.processor.config import load_config

DATA = Path(__file__).resolve().parents[1] / "data"
CIA402 = DATA / "cia402_drive.dbc"
CIA402_SIGNALS = """
[can]
dbc = "{dbc}"
[signals]
torque = "TPDO1.TorqueActual"
speed = "TPDO2.VelocityActual"
position = "TPDO2.PositionActual"
rated_torque = 0.32
increments_per_rev = 131072
"""
#: an ODrive's CANSimple frames of node 0: Get_Encoder_Estimates (0x09), Get_Iq (0x14)
CANSIMPLE_DBC = """VERSION ""
NS_ :
BS_:
BU_: ODrive Host
BO_ 9 Get_Encoder_Estimates: 8 ODrive
 SG_ Pos_Estimate : 0|32@1- (1,0) [0|0] "rev" Host
 SG_ Vel_Estimate : 32|32@1- (1,0) [0|0] "rev/s" Host
BO_ 20 Get_Iq: 8 ODrive
 SG_ Iq_Setpoint : 0|32@1- (1,0) [0|0] "A" Host
 SG_ Iq_Measured : 32|32@1- (1,0) [0|0] "A" Host
"""


def _config(tmp_path: Path, axes: str, head: str | None = None) -> Path:
    p = tmp_path / "machine.toml"
    p.write_text((head or CIA402_SIGNALS).format(dbc=CIA402) + axes)
    return p


def _ids(cfg_path: Path) -> dict[str, list[int]]:
    configs = load_config(cfg_path).axis_configs()
    return {n: [m.frame_id for m in c.protocol().messages] for n, c in configs.items()}


def test_cia402_rule_puts_each_tpdo_on_its_nodes_cob_id(tmp_path: Path) -> None:
    axes = "".join(f'[[axes]]\nname = "joint{n}"\nids = "cia402:{n}"\n' for n in (1, 2, 127))
    assert _ids(_config(tmp_path, axes)) == {
        "joint1": [0x181, 0x281], "joint2": [0x182, 0x282], "joint127": [0x1FF, 0x2FF]}


def test_cansimple_rule_puts_the_node_above_the_command(tmp_path: Path) -> None:
    dbc = tmp_path / "odrive.dbc"
    dbc.write_text(CANSIMPLE_DBC)
    head = (f'[can]\ndbc = "{dbc}"\n[signals]\ncurrent = "Get_Iq.Iq_Measured"\n'
            f'speed = "Get_Encoder_Estimates.Vel_Estimate"\n')
    axes = "[[axes]]\nname = \"a\"\nids = \"cansimple:3\"\n" \
           "[[axes]]\nname = \"b\"\nids = \"cansimple:62\"\n"
    # ID = node << 5 | command
    assert _ids(_config(tmp_path, axes, head)) == {
        "a": [3 << 5 | 0x14, 3 << 5 | 0x09], "b": [62 << 5 | 0x14, 62 << 5 | 0x09]}


def test_offset_rule_adds_to_the_dbcs_ids(tmp_path: Path) -> None:
    axes = '[[axes]]\nname = "m"\n[[axes]]\nname = "load"\nids = "offset:0x40"\n'
    assert _ids(_config(tmp_path, axes)) == {"m": [0x181, 0x281], "load": [0x1C1, 0x2C1]}


def test_each_axis_sets_its_own_signals_and_model_over_the_files(tmp_path: Path) -> None:
    axes = ('[[axes]]\nname = "a"\nids = "cia402:1"\n'
            '[[axes]]\nname = "b"\nids = "cia402:2"\n'
            '[axes.signals]\nrated_torque = 2.4\n[axes.model]\neffects = ["inertia"]\n')
    cfg = load_config(_config(tmp_path, axes + "[model]\neffects = [\"inertia\", \"viscous\"]\n"))
    a, b = cfg.axis("a"), cfg.axis("b")
    assert a.model["effects"] == ["inertia", "viscous"] and b.model["effects"] == ["inertia"]
    assert a.ratings().rated_torque == 0.32 and b.ratings().rated_torque == 2.4
    assert a.can["ids"] == "cia402:1" and b.can["ids"] == "cia402:2"
    assert not a.axes and not b.axes  # each axis's configuration is a one-axis one


def test_short_form_names_the_axes_after_their_nodes() -> None:
    assert parse_rules("cia402:1-3,7") == [(f"node{n}", IdRule("cia402", n)) for n in (1, 2, 3, 7)]
    assert parse_rules("offset:0,0x20") == [("axis1", IdRule("offset", 0)),
                                            ("axis2", IdRule("offset", 0x20))]
    assert str(parse_rule("offset:0x20", "ids")) == "offset:0x20"


def test_an_axis_less_configuration_is_one_axis(tmp_path: Path) -> None:
    cfg = load_config(_config(tmp_path, ""))
    assert cfg.one_axis() is cfg
    assert [m.frame_id for m in cfg.protocol().messages] == [0x181, 0x281]


def test_can_ids_moves_a_single_drive_too(tmp_path: Path) -> None:
    cfg = load_config(_config(tmp_path, "", CIA402_SIGNALS.replace("[signals]",
                                                                   'ids = "cia402:5"\n[signals]')))
    assert [m.frame_id for m in cfg.protocol().messages] == [0x185, 0x285]


_FIT = ["fit", "/dev/null"]
_BAD_AXES = [
    ('[[axes]]\nname = "a"\nids = "cia402:3"\n[[axes]]\nname = "b"\nids = "cia402:3"\n',
     "error: axes a and b both map feedback signal TPDO1.TorqueActual on ID 0x183: give "
     "each axis its own ID rule (ids = \"cia402:N\", ...) or its own signals"),
    ('[[axes]]\nname = "a"\n[[axes]]\nname = "b"\nids = "offset:0x600"\n',
     "error: axis b: DBC {dbc}: message TPDO2: ID rule offset:0x600 puts 0x281 at 0x881, "
     "outside the standard IDs 0x0..0x7FF"),
    ('[[axes]]\nname = "a"\nids = "cia402:128"\n',
     "error: {cfg}: axes[0].ids = cia402:128: cia402 node 128 is outside 1..127 "
     "(a CANopen node ID)"),
    ('[[axes]]\nname = "a"\nids = "cia402:0"\n',
     "error: {cfg}: axes[0].ids = cia402:0: cia402 node 0 is outside 1..127 "
     "(a CANopen node ID)"),
    ('[[axes]]\nname = "2nd"\n',
     "error: {cfg}: axes[0].name = '2nd': an axis name must be an identifier (letters, "
     "digits, _; not starting with a digit)"),
    ('[[axes]]\nname = "left-arm"\n',
     "error: {cfg}: axes[0].name = 'left-arm': an axis name must be an identifier (letters, "
     "digits, _; not starting with a digit)"),
    ('[[axes]]\nname = "linear"\n',
     "error: {cfg}: axes[0].name = 'linear': rotary and linear name the kind of axis "
     "(--axis rotary|linear), not an axis"),
    ('[[axes]]\nname = "a"\n[[axes]]\nname = "a"\nids = "cia402:2"\n',
     "error: {cfg}: axes[1].name = 'a': also the name of axes[0]"),
    ('[[axes]]\nname = "a"\nnode = 3\n',
     "error: {cfg}: axes[0]: unknown key node = 3 "
     "(valid: name, ids, own, dbc, eds, signals, model)"),
    ("".join(f'[[axes]]\nname = "a{i}"\nids = "offset:{i}"\n' for i in range(10_000)),
     "error: {cfg}: 10000 [[axes]] tables; canrls serves at most 127 axes on one bus"),
]


@pytest.mark.parametrize("axes,expected", _BAD_AXES)
def test_a_bad_machine_is_one_error_line(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                         axes: str, expected: str) -> None:
    cfg = _config(tmp_path, axes)
    line = cli_error(capsys, [*_FIT, "--config", str(cfg)])
    assert line == expected.format(cfg=cfg, dbc=CIA402)


@pytest.mark.parametrize("flag,expected", [
    ("cia402:126-128", "error: --axes cia402:126-128: cia402 node 128 is outside 1..127 "
                       "(a CANopen node ID)"),
    ("offset:1-10000", "error: --axes offset:1-10000: 10000 axes or more; canrls serves at "
                       "most 127 on one bus"),
    ("cia402:1,2,1", "error: --axes cia402:1,2,1: 1 is given twice"),
    ("canopen:1-2", "error: --axes canopen:1-2: expected RULE:LIST with RULE one of cia402, "
                    "cansimple, offset and LIST like 1-6 or 1,3,5"),
    ("cansimple:63", "error: --axes cansimple:63: cansimple node 63 is outside 0..62 (an "
                     "ODrive CANSimple node ID (63 is the broadcast))"),
])
def test_a_bad_short_form_is_one_error_line(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                            flag: str, expected: str) -> None:
    cfg = _config(tmp_path, "")
    assert cli_error(capsys, [*_FIT, "--config", str(cfg), "--axes", flag]) == expected


def test_axis_names_one_of_the_machines(tmp_path: Path,
                                        capsys: pytest.CaptureFixture[str]) -> None:
    cfg = str(_config(tmp_path, ""))
    assert cli_error(capsys, [*_FIT, "--config", cfg, "--axes", "cia402:1-2", "--axis",
                              "node3"]) == "error: --axis node3: no such axis (axes: node1, node2)"
    assert cli_error(capsys, [*_FIT, "--config", cfg, "--axis", "node3"]) == (
        "error: --axis node3: the configuration declares no axes ([[axes]] or --axes); "
        "--axis rotary|linear sets the kind of axis")


def test_a_rule_the_dbc_cannot_take_is_refused(tmp_path: Path) -> None:
    ext = tmp_path / "ext.dbc"
    ext.write_text(CIA402.read_text(encoding="cp1252").replace("BO_ 385 ", "BO_ 2147484033 ")
                   .replace("BO_ 385", "BO_ 2147484033"), encoding="cp1252")
    cfg = load_config(_config(tmp_path, '[[axes]]\nname = "a"\nids = "cia402:2"\n',
                              CIA402_SIGNALS.replace("{dbc}", str(ext))))
    with pytest.raises(ConfigError, match=r"axis a: .*message TPDO1: ID rule cia402:2: 0x181 "
                                          r"is an extended \(29-bit\) ID"):
        cfg.axis_configs()
