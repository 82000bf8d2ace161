"""A whole machine's log offline: ``canrls sim --axes N`` writes it, ``fit --axis NAME``
picks one axis, ``fit --axes`` fits every axis in one pass, and no frame of one axis is
ever decoded into another."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from canrls.can.logs import read_frames, write_log
from canrls.cli.main import main

AXES = "offset:0,0x10,0x20,0x30"
FIT = ["--kt", "0.1", "-e", "inertia,viscous,coulomb", "--json"]


@pytest.fixture(scope="module")
def machine_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("machine") / "machine.log"
    assert main(["sim", "--out", str(out), "--duration", "6", "--axes", "4", "--seed", "2"]) == 0
    return out


def _json(capsys: pytest.CaptureFixture[str], argv: list[str]) -> dict:
    capsys.readouterr()
    assert main(argv) == 0
    return json.loads(capsys.readouterr().out)


def test_sim_writes_each_axis_on_its_own_ids_with_its_own_truth(
        machine_log: Path, capsys: pytest.CaptureFixture[str]) -> None:
    ids: dict[int, int] = {}
    for b in read_frames(machine_log):
        for i, n in zip(*np.unique(b.arbitration_id, return_counts=True), strict=True):
            ids[int(i)] = ids.get(int(i), 0) + int(n)
    assert ids == {i + k * 0x10: 6000 for k in range(4) for i in (0x101, 0x102)}
    fits = _json(capsys, ["fit", str(machine_log), "--axes", AXES, *FIT])["axes"]
    # each axis its own inertia (x 1 + 0.5 k of the default 2e-4 kg m²)
    for k in range(4):
        j = fits[f"axis{k + 1}"]["parameters"]["inertia.J"]["value"]
        assert j == pytest.approx(2e-4 * (1 + 0.5 * k), rel=0.02)


def test_fit_of_all_axes_in_one_pass_equals_each_axis_alone(
        machine_log: Path, capsys: pytest.CaptureFixture[str]) -> None:
    every = _json(capsys, ["fit", str(machine_log), "--axes", AXES, *FIT])
    assert every["frames"] == {"total": 48000, "unknown_axis": 0}
    for name in ("axis1", "axis3"):
        one = _json(capsys, ["fit", str(machine_log), "--axes", AXES, "--axis", name, *FIT])
        assert every["axes"][name]["parameters"] == one["parameters"]
        assert every["axes"][name]["frames"] == one["frames"]
        assert one["frames"]["foreign"] == 36000  # the other three axes', counted


def test_each_axis_searches_its_stribeck_speed_as_alone(
        machine_log: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # Stribeck friction without a speed configured: fit searches the speed on the record,
    # each axis on its own frames, in one pass as alone
    fit = ["--kt", "0.1", "-e", "inertia,viscous,coulomb,stribeck", "--json"]
    every = _json(capsys, ["fit", str(machine_log), "--axes", AXES, *fit])
    for name in ("axis1", "axis3"):
        one = _json(capsys, ["fit", str(machine_log), "--axes", AXES, "--axis", name, *fit])
        assert [s["key"] for s in one["search"]] == ["stribeck_speed"]
        assert every["axes"][name]["search"] == one["search"]
        assert every["axes"][name]["parameters"] == one["parameters"]


def test_frames_of_other_axes_are_never_decoded_into_one(
        machine_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # axis 2 alone: its frames only, on its own IDs
    mine = []
    for b in read_frames(machine_log):
        sel = b.take((b.arbitration_id == 0x111) | (b.arbitration_id == 0x112))
        mine.append(sel)
    alone = tmp_path / "axis2.log"
    write_log(alone, mine)
    two = _json(capsys, ["fit", str(alone), "--axes", "offset:0x10", *FIT])
    among = _json(capsys, ["fit", str(machine_log), "--axes", AXES, "--axis", "axis2", *FIT])
    assert among["parameters"] == two["parameters"]
    assert two["frames"]["foreign"] == 0 and among["frames"]["foreign"] == 36000


def test_frames_of_no_axis_are_counted(machine_log: Path,
                                       capsys: pytest.CaptureFixture[str]) -> None:
    d = _json(capsys, ["fit", str(machine_log), "--axes", "offset:0,0x10", *FIT])
    assert d["frames"] == {"total": 48000, "unknown_axis": 24000}
    assert sorted(d["axes"]) == ["axis1", "axis2"]


def test_first_line_says_how_many_axes(machine_log: Path,
                                       capsys: pytest.CaptureFixture[str]) -> None:
    capsys.readouterr()
    assert main(["fit", str(machine_log), "--axes", AXES, "--kt", "0.1"]) == 0
    first = capsys.readouterr().out.splitlines()[0]
    assert first == f"{machine_log}: 4 of 4 axes identified, 48000 frames, 0 of no axis"


def test_diagnose_validate_and_export_pick_one_axis(
        machine_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    model = tmp_path / "axis2.json"
    base = [str(machine_log), "--axes", AXES, "--axis", "axis2", "--kt", "0.1"]
    capsys.readouterr()
    assert main(["fit", *base, "--save-model", str(model)]) == 0
    diag = _json(capsys, ["diagnose", *base, "--json"])
    # axis 2's hidden effect is its unbalance
    assert diag["candidates"][0]["effect"] == "unbalance", diag["candidates"][0]
    # the saved model keeps the axis's ID rule: axis 2's frames, not axis 1's
    val = _json(capsys, ["validate", str(machine_log), "--model", str(model), "--json"])
    assert val["frames"]["foreign"] == 36000
    capsys.readouterr()
    assert main(["export-c", "--model", str(model), "--out", str(tmp_path / "c")]) == 0
    # the target decodes axis 2's IDs
    model_c = (tmp_path / "c" / "canrls_model.c").read_text()
    assert "/* DriveCurrent */ {.id = 273u" in model_c  # 0x101 + 0x10
    assert "/* DriveSpeed */ {.id = 274u" in model_c


@pytest.mark.parametrize("kind,names", [("cia402", ["node1", "node2", "node3"]),
                                        ("cansimple", ["node0", "node1", "node2"])])
def test_a_machine_of_cia402_or_cansimple_nodes_reads_back_as_sim_says(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], kind: str, names: list[str]
) -> None:
    log = tmp_path / f"{kind}.log"
    capsys.readouterr()
    assert main(["sim", "--out", str(log), "--duration", "4", "--axes", "3", "--ids", kind,
                 "--seed", "3"]) == 0
    first = capsys.readouterr().out.splitlines()[0]
    # the first line says how to read the log back: those very options
    options = first.split("; canrls fit ", 1)[1].rstrip(")").split()
    # a CiA 402 node reports its torque (no Kt then), an ODrive its current
    kt = [] if kind == "cia402" else ["--kt", "0.1"]
    d = _json(capsys, ["fit", str(log), *options, *kt, "--json"])
    assert d["frames"] == {"total": 24000, "unknown_axis": 0}
    assert list(d["axes"]) == names
    for k, name in enumerate(names):
        j = d["axes"][name]["parameters"]["inertia.J"]["value"]
        assert j == pytest.approx(2e-4 * (1 + 0.5 * k), rel=0.02)
