"""A CiA 402 drive from its EDS (``--eds``): the TPDOs and roles canopen reads, the ratings
of its defaults, and the same answer as through the equivalent DBC."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from cli_tool import cli_error

from canrls.can.eds import read_eds
from canrls.cli.main import main

pytest.importorskip("canopen")

DATA = Path(__file__).resolve().parents[1] / "data"
EDS = DATA / "cia402_drive.eds"


def test_the_eds_gives_tpdos_roles_and_ratings() -> None:
    d = read_eds(EDS)
    assert d.signals == ("torque=TPDO1.TorqueActualValue", "current=TPDO1.CurrentActualValue",
                         "position=TPDO2.PositionActualValue",
                         "speed=TPDO2.VelocityActualValue")
    # 0x6076 = 320 mN·m, 0x6075 = 5000 mA; no 0x608F: increments asked for by flag
    assert (d.ratings.rated_torque, d.ratings.rated_current) == (0.32, 5.0)
    assert d.ratings.increments_per_rev is None
    assert "BO_ 385 TPDO1: 6 Drive" in d.dbc_text and "BO_ 641 TPDO2: 8 Drive" in d.dbc_text


@pytest.fixture(scope="module")
def nodes_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("eds") / "nodes.log"
    assert main(["sim", "--out", str(out), "--duration", "4", "--axes", "2", "--ids",
                 "cia402", "--seed", "6"]) == 0
    return out


def test_fit_through_the_eds_equals_fit_through_the_dbc(
        nodes_log: Path, capsys: pytest.CaptureFixture[str]) -> None:
    capsys.readouterr()
    assert main(["fit", str(nodes_log), "--eds", str(EDS), "--increments-per-rev", "131072",
                 "--axes", "cia402:1-2", "--json"]) == 0
    eds = json.loads(capsys.readouterr().out)["axes"]
    dbc = DATA / "cia402_drive.dbc"
    assert main(["fit", str(nodes_log), "--dbc", str(dbc), "--signal", "torque=TPDO1.TorqueActual",
                 "--signal", "current=TPDO1.CurrentActual", "--signal",
                 "speed=TPDO2.VelocityActual", "--signal", "position=TPDO2.PositionActual",
                 "--rated-torque", "0.32", "--rated-current", "5", "--increments-per-rev",
                 "131072", "--axes", "cia402:1-2", "--json"]) == 0
    ref = json.loads(capsys.readouterr().out)["axes"]
    for node in ("node1", "node2"):
        assert eds[node]["parameters"] == ref[node]["parameters"]
    assert eds["node2"]["parameters"]["inertia.J"]["value"] == pytest.approx(3e-4, rel=0.02)


def test_a_rating_the_eds_lacks_is_asked_for_by_its_flag(
        nodes_log: Path, capsys: pytest.CaptureFixture[str]) -> None:
    line = cli_error(capsys, ["fit", str(nodes_log), "--eds", str(EDS), "--axes", "cia402:1"])
    assert line.startswith("error: ") and "--increments-per-rev" in line


def test_an_eds_without_402_objects_in_its_tpdos_is_refused(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.eds"
    bad.write_text(EDS.read_text().replace("DefaultValue=0x60770010", "DefaultValue=0x60410010")
                   .replace("DefaultValue=0x60780010", "DefaultValue=0x60410010")
                   .replace("DefaultValue=0x60640020", "DefaultValue=0x60410010")
                   .replace("DefaultValue=0x606C0020", "DefaultValue=0x60410010"))
    assert cli_error(capsys, ["fit", "/dev/null", "--eds", str(bad)]) == (
        f"error: EDS {bad}: no TPDO maps the torque, current, velocity or position actual "
        f"value (0x6077, 0x6078, 0x606C, 0x6064)")


def test_a_dbc_and_an_eds_together_are_refused(capsys: pytest.CaptureFixture[str]) -> None:
    line = cli_error(capsys, ["fit", "/dev/null", "--eds", str(EDS), "--dbc",
                              str(DATA / "cia402_drive.dbc")])
    assert line.endswith("give a DBC (can.dbc, --dbc) or an EDS (can.eds, --eds), not both")
