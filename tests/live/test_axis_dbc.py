"""``canrls export-dbc``: cantools decodes every axis's own frames of a machine's daemons
on a virtual bus with the DBC it writes, each message named after its axis."""

from __future__ import annotations

import os
from pathlib import Path

import can
import cantools
import pytest
from cli_tool import cli_error
from daemon_tool import axis_daemons

from canrls.cli.main import main
from canrls.sim.machine import machine, machine_frames

MACHINE = ('[model]\nkt = 0.1\n[daemon]\npublish_interval = 0.05\n'
           '[[axes]]\nname = "left"\n[[axes]]\nname = "right"\nids = "offset:0x10"\n'
           'own = "offset:0x80"\n')


def test_cantools_decodes_each_axis_of_a_daemon_run(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg_path = tmp_path / "machine.toml"
    cfg_path.write_text(MACHINE)
    dbc = tmp_path / "machine.dbc"
    capsys.readouterr()
    assert main(["export-dbc", "--config", str(cfg_path), "--out", str(dbc)]) == 0
    assert capsys.readouterr().out == (f"{dbc}: canrls' own frames of left, right "
                                       f"(20 messages)\n")
    db = cantools.database.load_file(str(dbc))
    ch = f"axis-dbc-{os.getpid()}"
    feed = can.Bus(interface="virtual", channel=ch, preserve_timestamps=True,
                   ignore_config=True)
    tool = can.Bus(interface="virtual", channel=ch, ignore_config=True)
    reader = can.BufferedReader()
    notifier = can.Notifier(tool, [reader], timeout=0.05)
    daemons = axis_daemons(cfg_path, {"interface": "virtual", "channel": ch})
    try:
        for d in daemons.values():
            d.start()
        n = 0
        for block in machine_frames(machine(2, duration=4.0, seed=4)):
            for m in block.to_messages("ch"):
                feed.send(m)
                n += 1
        for d in daemons.values():
            assert d.wait_for(lambda x: x.stats().frames >= n, 60)
    finally:
        for d in daemons.values():
            d.stop()  # publishes its final state
        notifier.stop()
        feed.shutdown()
        tool.shutdown()
    frames = []
    while (m := reader.get_message(0.0)) is not None:
        frames.append(m)
    feedback = {m.frame_id for d in daemons.values() for m in d.protocol.messages}
    own = [m for m in frames if m.arbitration_id not in feedback]
    assert own
    names: dict[str, int] = {}
    for m in own:  # every frame a daemon sent is in the DBC, under its axis's name
        msg = db.get_message_by_frame_id(m.arbitration_id)
        msg.decode(m.data)
        names[msg.name] = names.get(msg.name, 0) + 1
    for axis, d in daemons.items():
        status = [db.decode_message(f"{axis}_RlsStatus", m.data) for m in own
                  if db.get_message_by_frame_id(m.arbitration_id).name == f"{axis}_RlsStatus"]
        assert status, f"no RlsStatus of axis {axis}"
        # the last status on the bus, read by cantools, is the daemon's own
        assert d.last_status is not None
        assert status[-1]["UpdateCount"] == d.last_status.update_count > 0
        assert status[-1]["ResidualRms"] == pytest.approx(d.last_status.residual_rms,
                                                          rel=1e-6)
        for msg in ("RlsEstimate", "RlsParamInfo", "RlsHealth", "RlsCounters"):
            assert names.get(f"{axis}_{msg}", 0) > 0
    # right's own frames are on the shipped IDs + 0x80
    assert db.get_message_by_name("right_RlsStatus").frame_id == 0x310 + 0x80
    assert db.get_message_by_name("right_RlsCommand").frame_id == 0x320 + 0x80


def test_export_dbc_refuses_an_unknown_axis_and_colliding_frames(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg_path = tmp_path / "machine.toml"
    cfg_path.write_text(MACHINE)
    out = tmp_path / "m.dbc"
    assert cli_error(capsys, ["export-dbc", "--config", str(cfg_path), "--axis", "middle",
                              "--out", str(out)]) == (
        "error: --axis middle: no such axis (axes: left, right)")
    cfg_path.write_text(MACHINE.replace('own = "offset:0x80"', 'own = "offset:0x0"'))
    assert cli_error(capsys, ["export-dbc", "--config", str(cfg_path), "--out",
                              str(out)]).startswith(
        "error: axis right's RlsEstimate and axis left's RlsEstimate would both be on ID")
    assert not out.exists()  # nothing written
