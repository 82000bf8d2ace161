"""Axes of different kinds in one machine: a CiA 402 node and an ODrive CANSimple node on
one bus, each with its own DBC, ID rule, ratings and Kt, declared in ``[[axes]]`` or by
``--axis NAME ...`` groups on the command line: fitted, served and monitored per axis."""

from __future__ import annotations

import dataclasses
import json
import os
import threading
import time
from pathlib import Path

import can
import pytest
from cli_tool import cli_error
from daemon_tool import axis_daemons

from canrls.can.logs import read_frames, write_log
from canrls.cli.main import main
from canrls.live.machine_daemon import MachineDaemon
from canrls.sim.machine import kind_dbc, machine, machine_frames

CIA = str(kind_dbc("cia402"))
ODRIVE = str(kind_dbc("cansimple"))
JOINT = ["torque=TPDO1.TorqueActual", "current=TPDO1.CurrentActual",
         "speed=TPDO2.VelocityActual", "position=TPDO2.PositionActual"]
WHEEL = ["current=Get_Iq.Iq_Measured", "speed=Get_Encoder_Estimates.Vel_Estimate",
         "position=Get_Encoder_Estimates.Pos_Estimate"]
#: the same machine as --axis groups
GROUPS = ["--axis", "joint", "--ids", "cia402:1", "--dbc", CIA,
          *[x for s in JOINT for x in ("--signal", s)], "--rated-torque", "0.32",
          "--rated-current", "5", "--increments-per-rev", "131072",
          "--axis", "wheel", "--ids", "cansimple:0", "--dbc", ODRIVE, "--kt", "0.1",
          *[x for s in WHEEL for x in ("--signal", s)]]


def _toml_signals(items: list[str]) -> str:
    return ", ".join(f'{r} = "{s}"' for r, s in (i.split("=") for i in items))


MACHINE = (f'[daemon]\npublish_interval = 0.05\n'
           f'[[axes]]\nname = "joint"\nids = "cia402:1"\ndbc = "{CIA}"\n'
           f'signals = {{ {_toml_signals(JOINT)}, rated_torque = 0.32, rated_current = 5.0, '
           f'increments_per_rev = 131072 }}\n'
           f'[[axes]]\nname = "wheel"\nids = "cansimple:0"\ndbc = "{ODRIVE}"\n'
           f'model = {{ kt = 0.1 }}\nsignals = {{ {_toml_signals(WHEEL)} }}\n')


@pytest.fixture(scope="module")
def bus_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """4 s of a CiA 402 node 1 and an ODrive node 0 on one bus (seeded)."""
    a = machine(1, duration=4, seed=3, kind="cia402", hidden=[""])
    b = machine(1, duration=4, seed=4, kind="cansimple", hidden=[""])
    axes = (dataclasses.replace(a[0], name="joint"), dataclasses.replace(b[0], name="wheel"))
    out = tmp_path_factory.mktemp("kinds") / "machine.log"
    write_log(out, list(machine_frames(axes)))
    return out


def _fit(capsys: pytest.CaptureFixture[str], *argv: str) -> dict:
    capsys.readouterr()
    assert main(["fit", *argv, "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def test_fit_each_kind_through_axes_tables_and_through_groups(
        bus_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = tmp_path / "machine.toml"
    cfg.write_text(MACHINE)
    tables = _fit(capsys, str(bus_log), "--config", str(cfg))["axes"]
    groups = _fit(capsys, str(bus_log), *GROUPS)["axes"]
    assert sorted(tables) == sorted(groups) == ["joint", "wheel"]
    for name in ("joint", "wheel"):
        assert tables[name]["parameters"] == groups[name]["parameters"]
        # J = 2e-4 kg·m², B = 1e-4 N·m·s/rad of both simulated drives
        p = tables[name]["parameters"]
        assert p["inertia.J"]["value"] == pytest.approx(2e-4, rel=0.01)
        assert p["viscous.B"]["value"] == pytest.approx(1e-4, rel=0.02)
    # --axis NAME again, alone, picks one of the groups
    one = _fit(capsys, str(bus_log), *GROUPS, "--axis", "wheel")
    assert one["parameters"] == groups["wheel"]["parameters"]


@pytest.mark.parametrize("argv,expected", [
    (["--axis", "a", "--ids", "cia402:200"],
     "error: --axis a --ids = cia402:200: cia402 node 200 is outside 1..127 (a CANopen "
     "node ID)"),
    (["--axis", "a", "--ids", "cia402:1", "--axis", "a", "--ids", "cia402:2"],
     "error: --axis a: two --axis groups of that name"),
    (["--axis", "a", "--dbc", CIA, "--signal", "speed=TPDO2.Nope"],
     "error: --axis a: "),
    (["--axes", "cia402:1-2", "--axis", "a", "--ids", "cia402:3"],
     "error: --axis a --ids cia402:3: with --axes cia402:1-2 the rule gives each axis's IDs"),
])
def test_a_bad_group_is_one_error_naming_it(
        capsys: pytest.CaptureFixture[str], argv: list[str], expected: str) -> None:
    assert cli_error(capsys, ["fit", "/dev/null", *argv]).startswith(expected)


def test_ids_outside_a_group_is_a_usage_error(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as e:
        main(["fit", "/dev/null", "--ids", "cia402:1"])
    assert e.value.code == 2
    assert "--ids cia402:1: belongs to an --axis NAME group" in capsys.readouterr().err


def test_one_daemon_serves_and_the_monitor_shows_both_kinds(
        bus_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg_path = tmp_path / "machine.toml"
    cfg_path.write_text(MACHINE)
    ch = f"axes-kinds-{os.getpid()}"
    daemons = axis_daemons(cfg_path, {"interface": "virtual", "channel": ch},
                           backpressure=True, block_interval=0.002, rx_filter=True)
    md = MachineDaemon(daemons)
    feed = can.Bus(interface="virtual", channel=ch, preserve_timestamps=True,
                   ignore_config=True)
    frames = [m for b in read_frames(bus_log) for m in b.to_messages("can0")]
    shown: dict = {}

    def monitor() -> None:
        shown["rc"] = main(["monitor", "--config", str(cfg_path), "-i", "virtual", "-c", ch,
                            "--once", "--json", "--timeout", "30"])

    try:
        md.start()
        for m in frames:
            feed.send(m)
        assert md.wait_for(lambda x: all(d.stats().frames >= len(frames) // 2
                                         for d in x.daemons.values()), 120)
        capsys.readouterr()
        t = threading.Thread(target=monitor)
        t.start()
        t.join(60)
        time.sleep(0.1)
    finally:
        md.stop()
        feed.shutdown()
    assert shown["rc"] == 0
    view = json.loads(capsys.readouterr().out)["axes"]
    assert sorted(view) == ["joint", "wheel"]
    for name, d in daemons.items():
        off = _fit(capsys, str(bus_log), "--config", str(cfg_path), "--axis", name)
        live = d.estimates()
        assert [p.name for p in live.parameters] == list(off["parameters"])
        for p in live.parameters:  # live equals offline, per axis and kind
            assert p.value == pytest.approx(off["parameters"][p.name]["value"], rel=1e-6)
        assert view[name]["parameters"]["inertia.J"]["unit"] == "kg·m²"
        assert view[name]["update_count"] > 0
