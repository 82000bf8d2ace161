"""Two axes' daemons on one bus: each publishes on its own IDs ([daemon] own_ids, the
axis's index x 0x40 by default) and a command reaches only the axis it addresses."""

from __future__ import annotations

import dataclasses
import json
import os
import time
from pathlib import Path

import can
import numpy as np
import pytest
from cli_tool import cli_error

from canrls.can.estimator_frames import CommandCode, CommandResult, FrameDecoder, encode_command
from canrls.can.logs import read_frames, write_log
from canrls.cli.main import main
from canrls.live.bus_link import messages_to_block, moved
from canrls.live.daemon import Daemon
from canrls.live.daemon_settings import DaemonSettings
from canrls.live.machine_daemon import MachineDaemon
from canrls.live.monitor_listener import Monitor
from canrls.processor.config import load_config
from canrls.sim.machine import machine, machine_frames

OWN = range(0x300, 0x322)  # the shipped DBC's own frames, RlsEstimate .. RlsCommandAck


def _machine(tmp_path: Path) -> dict:
    p = tmp_path / "machine.toml"
    p.write_text('[model]\nkt = 0.1\n[daemon]\ncommands = true\npublish_interval = 0.05\n'
                 '[[axes]]\nname = "a"\n[[axes]]\nname = "b"\nids = "offset:0x10"\n')
    return load_config(p).axis_configs()


def test_each_axis_publishes_on_its_own_ids_and_obeys_its_own_commands(
        tmp_path: Path) -> None:
    axes = _machine(tmp_path)
    ch = f"axes-live-{os.getpid()}"
    feed = can.Bus(interface="virtual", channel=ch, preserve_timestamps=True,
                   ignore_config=True)
    tool = can.Bus(interface="virtual", channel=ch, ignore_config=True)
    reader = can.BufferedReader()
    notifier = can.Notifier(tool, [reader], timeout=0.05)
    daemons = {}
    try:
        for name, cfg in axes.items():
            protocol = cfg.protocol()
            d = Daemon(protocol, cfg.model_for(protocol), cfg.settings(),
                       DaemonSettings.from_config(cfg), bus={"interface": "virtual",
                                                            "channel": ch})
            d.start()
            daemons[name] = d
        sim = machine(2, duration=2.0, seed=4)
        n = 0
        for block in machine_frames(sim):
            for m in block.to_messages("ch"):
                feed.send(m)
                n += 1
        for d in daemons.values():
            assert d.wait_for(lambda x: x.stats().frames >= n, 60)  # the machine's and more
        # freeze axis b: its RlsCommand is 0x320 + 0x40
        feed.send(moved(encode_command(CommandCode.FREEZE), 0x40))
        assert daemons["b"].wait_for(lambda x: x.pipeline.frozen, 10)
        time.sleep(0.3)
        assert not daemons["a"].pipeline.frozen  # the command reached b only
        frames: list[can.Message] = []
        while (m := reader.get_message(0.0)) is not None:
            frames.append(m)
        ids = {m.arbitration_id for m in frames}
        a_ids = {i for i in ids if i in OWN}
        b_ids = {i for i in ids if i - 0x40 in OWN}
        assert 0x310 in a_ids and 0x350 in b_ids  # both publish their RlsStatus
        assert 0x361 in b_ids and 0x321 not in a_ids  # b's ack on b's ID, none from a
        # b's own frames decode as the shipped DBC's once moved back
        dec = FrameDecoder()
        dec.feed_all([moved(m, -0x40) for m in frames if m.arbitration_id in b_ids])
        assert dec.acks and dec.acks[-1].result is CommandResult.OK
        # the monitor of axis b reads b's frames only
        mon = Monitor(own_offset=0x40, feedback_ids=[0x111, 0x112])
        for m in frames:
            mon.on_message_received(m)
        view = mon.snapshot()
        assert view.totals["estimator"] == sum(1 for m in frames if m.arbitration_id in b_ids
                                               and m.arbitration_id != 0x360)
        assert view.totals["command"] == 1  # the freeze sent to b
        # a's own frames (and a's feedback) are another axis's
        assert view.totals["other"] == sum(1 for m in frames
                                           if m.arbitration_id not in b_ids | {0x111, 0x112})
        assert view.totals["other"] >= sum(1 for m in frames if m.arbitration_id in a_ids) > 0
        assert view.last_ack is not None and view.last_ack.result is CommandResult.OK
        assert view.status is not None and view.status.frozen
    finally:
        for d in daemons.values():
            d.stop()
        notifier.stop()
        feed.shutdown()
        tool.shutdown()


@pytest.mark.parametrize("axes,expected", [
    ('[[axes]]\nname = "a"\n[[axes]]\nname = "b"\nids = "offset:0x10"\nown = "offset:0x0"\n',
     "error: axis b's RlsEstimate and axis a's RlsEstimate would both be on ID 0x300: give "
     "the axis another own = \"offset:N\""),
    ('[[axes]]\nname = "a"\n[[axes]]\nname = "b"\nids = "offset:0x1ff"\n',
     "error: axis a's RlsEstimate and axis b's feedback DriveCurrent would both be on ID "
     "0x300: give the axis another own = \"offset:N\""),
    ('[[axes]]\nname = "a"\nown = "offset:0x4e0"\n',
     "error: axis a's RlsCommand would be on ID 0x800, outside the standard IDs 0x0..0x7FF: "
     "give the axis another own = \"offset:N\""),
    ('[[axes]]\nname = "a"\nown = "cia402:3"\n',
     "error: {cfg}: axes[0].own = 'cia402:3': canrls' own frames move by an offset only "
     "(\"offset:N\")"),
])
def test_own_frames_that_collide_are_refused_naming_both(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], axes: str, expected: str) -> None:
    p = tmp_path / "m.toml"
    p.write_text(axes)
    assert cli_error(capsys, ["fit", "/dev/null", "--config", str(p)]) == expected.format(cfg=p)


def test_live_equals_fit_axis_on_the_recorded_bus(tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    """One process serving both axes of a machine: each axis's estimates equal canrls fit
    --axis NAME of the machine's log within 1e-6 relative."""
    log = tmp_path / "machine.log"
    assert main(["sim", "--out", str(log), "--duration", "4", "--axes", "2", "--seed", "5"]) == 0
    cfg_path = tmp_path / "machine.toml"
    cfg_path.write_text('[model]\nkt = 0.1\n[[axes]]\nname = "a"\n'
                        '[[axes]]\nname = "b"\nids = "offset:0x10"\n')
    ch = f"axes-live-eq-{os.getpid()}"
    daemons = {}
    for name, cfg in load_config(cfg_path).axis_configs().items():
        protocol = cfg.protocol()
        # each axis its own frames only, as canrls run of a machine takes them
        dset = dataclasses.replace(DaemonSettings.from_config(cfg), block_interval=0.002,
                                   rx_filter=True)
        daemons[name] = Daemon(protocol, cfg.model_for(protocol), cfg.settings(), dset,
                               bus={"interface": "virtual", "channel": ch}, backpressure=True)
    machine_d = MachineDaemon(daemons)
    feed = can.Bus(interface="virtual", channel=ch, preserve_timestamps=True,
                   ignore_config=True)
    clean = [m for b in read_frames(log) for m in b.to_messages("can0")]
    # a fault on axis a: garbage on its DriveCurrent's ID (the CRC fails), seeded
    rng = np.random.default_rng(11)
    frames = []
    for i, m in enumerate(clean):
        frames.append(m)
        if i % 50 == 7:
            frames.append(can.Message(timestamp=m.timestamp, arbitration_id=0x101,
                                      is_extended_id=False, data=rng.bytes(8)))
    fed = tmp_path / "fed.log"
    write_log(fed, [messages_to_block(frames)])
    try:
        machine_d.start()
        for m in frames:
            feed.send(m)
        assert machine_d.wait_for(lambda x: all(
            d.processor.frame_counts().messages and sum(
                d.processor.frame_counts().messages.values()) + sum(
                d.processor.rejected.values()) >= 8000
            for d in x.daemons.values()), 120)
        time.sleep(0.2)
    finally:
        machine_d.stop()
        feed.shutdown()
    def fit(path: Path, name: str) -> dict:
        capsys.readouterr()
        assert main(["fit", str(path), "--config", str(cfg_path), "--axis", name,
                     "--json"]) == 0
        return json.loads(capsys.readouterr().out)

    assert daemons["a"].processor.rejected["crc"] == fit(fed, "a")["frames"]["rejected"]["crc"] > 0
    # the bus's filters: b never took a's frames nor a's own, a took b's neither
    assert daemons["b"].stats().frames == 8000
    assert daemons["a"].stats().frames == 8000 + len(frames) - len(clean)
    # axis b's estimates are those of the clean log: a's fault never reached it
    assert fit(fed, "b")["parameters"] == fit(log, "b")["parameters"]
    for name, d in daemons.items():
        off = fit(fed, name)["parameters"]
        live = d.estimates()
        assert [p.name for p in live.parameters] == list(off)
        for p in live.parameters:
            assert p.value == pytest.approx(off[p.name]["value"], rel=1e-6), (name, p.name)
            assert p.fixed == pytest.approx(off[p.name]["fixed"], rel=1e-6), (name, p.name)


def test_canrls_run_serves_every_axis_with_its_own_checkpoint(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = tmp_path / "machine.toml"
    cfg.write_text(f'[model]\nkt = 0.1\n[daemon]\ncheckpoint = "{tmp_path / "ck.bin"}"\n'
                   '[[axes]]\nname = "a"\n[[axes]]\nname = "b"\nids = "offset:0x10"\n')
    capsys.readouterr()
    assert main(["run", "--config", str(cfg), "-i", "virtual", "-c",
                 f"axes-run-{os.getpid()}", "--duration", "0.3", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert sorted(out["axes"]) == ["a", "b"]
    assert all("daemon" in v and "parameters" in v for v in out["axes"].values())
    assert (tmp_path / "ck.a.bin").is_file() and (tmp_path / "ck.b.bin").is_file()
    assert not (tmp_path / "ck.bin").exists()


def test_monitor_shows_one_row_per_axis(tmp_path: Path,
                                        capsys: pytest.CaptureFixture[str]) -> None:
    cfg_path = tmp_path / "machine.toml"
    cfg_path.write_text('[model]\nkt = 0.1\n[daemon]\npublish_interval = 0.05\n'
                        'info_interval = 0.2\n[[axes]]\nname = "a"\n'
                        '[[axes]]\nname = "b"\nids = "offset:0x10"\n'
                        '[axes.model]\neffects = ["inertia", "viscous"]\n')
    ch = f"axes-mon-{os.getpid()}"
    daemons = {}
    for name, cfg in load_config(cfg_path).axis_configs().items():
        protocol = cfg.protocol()
        daemons[name] = Daemon(protocol, cfg.model_for(protocol), cfg.settings(),
                               DaemonSettings.from_config(cfg),
                               bus={"interface": "virtual", "channel": ch})
    machine_d = MachineDaemon(daemons)
    argv = ["monitor", "--config", str(cfg_path), "-i", "virtual", "-c", ch, "--once",
            "--timeout", "10"]
    try:
        machine_d.start()
        capsys.readouterr()
        assert main([*argv, "--json"]) == 0
        views = json.loads(capsys.readouterr().out)["axes"]
        assert main(argv) == 0
        text = capsys.readouterr().out.splitlines()
    finally:
        machine_d.stop()
    # each axis's parameters, from its own frames only
    assert list(views["a"]["parameters"]) == ["inertia.J", "viscous.B", "coulomb.Tc"]
    assert list(views["b"]["parameters"]) == ["inertia.J", "viscous.B"]
    assert text[0].endswith("2 axes")
    assert [ln.split()[0] for ln in text[2:4]] == ["a", "b"]


def test_sighup_adds_and_removes_axes_without_touching_the_others(tmp_path: Path) -> None:
    cfg_path = tmp_path / "machine.toml"
    head = '[model]\nkt = 0.1\n[daemon]\npublish_interval = 0.05\n'

    def axis(name: str, ids: int, own: str = "") -> str:
        return (f'[[axes]]\nname = "{name}"\nids = "offset:{ids:#x}"\n'
                + (f'own = "offset:{own}"\n' if own else ""))

    # own frames by index: a 0x300.., b 0x340.., c 0x380..
    cfg_path.write_text(head + axis("a", 0) + axis("b", 0x10) + axis("c", 0x20))
    ch = f"axes-hup-{os.getpid()}"

    def build(name: str) -> Daemon:
        cfg = load_config(cfg_path).axis(name)
        protocol = cfg.protocol()
        dset = dataclasses.replace(DaemonSettings.from_config(cfg), rx_filter=True)
        return Daemon(protocol, cfg.model_for(protocol), cfg.settings(), dset,
                      bus={"interface": "virtual", "channel": ch})

    def axes() -> list[str]:
        return list(load_config(cfg_path).axis_configs())

    md = MachineDaemon({n: build(n) for n in axes()}, build=build, axes=axes)
    md.start()
    try:
        a, c = md.daemons["a"], md.daemons["c"]
        published = a.stats().publications
        # b removed, e added with own frames of its own
        cfg_path.write_text(head + axis("a", 0) + axis("c", 0x20) + axis("e", 0x30, "0xc0"))
        md.request_reload()
        md.reconcile()
        assert sorted(md.daemons) == ["a", "c", "e"]
        assert md.daemons["a"] is a and md.daemons["c"] is c  # they run on untouched
        assert md.wait_for(lambda x: x.daemons["e"].stats().publications > 0, 10)
        assert a.stats().publications > published and a.failure is None
        # d by its index would publish on 0x380..: running c's own frames (c keeps its
        # IDs until a restart): refused, nothing changes, e is not removed either
        cfg_path.write_text(head + axis("a", 0) + axis("c", 0x20) + axis("d", 0x40))
        md.request_reload()
        md.reconcile()
        assert sorted(md.daemons) == ["a", "c", "e"]
    finally:
        md.stop()


def test_the_simulated_machine_as_a_bus_feeds_every_axis(tmp_path: Path) -> None:
    """``-i canrls-sim`` with ``axes=3``: three drives on one bus, each axis's daemon
    identifies its own drive (inertia x 1, 1.5, 2 of the default)."""
    cfg_path = tmp_path / "machine.toml"
    cfg_path.write_text('[model]\nkt = 0.1\n[daemon]\npublish_interval = 0.05\n' + "".join(
        f'[[axes]]\nname = "axis{k + 1}"\nids = "offset:{k * 0x10:#x}"\n' for k in range(3)))
    ch = f"axes-simbus-{os.getpid()}"
    # in real time: every axis's bus joins the drive before it has sent much
    bus = {"interface": "canrls-sim", "channel": ch, "axes": 3, "seed": 2, "duration": 4.0}
    daemons = {}
    for name, cfg in load_config(cfg_path).axis_configs().items():
        protocol = cfg.protocol()
        dset = dataclasses.replace(DaemonSettings.from_config(cfg), rx_filter=True)
        daemons[name] = Daemon(protocol, cfg.model_for(protocol), cfg.settings(), dset,
                               bus=bus)
    md = MachineDaemon(daemons)
    try:
        md.start()
        assert md.wait_for(lambda x: all(d.stats().frames >= 7000
                                         for d in x.daemons.values()), 30)
    finally:
        md.stop()
    for k, (name, d) in enumerate(daemons.items()):
        j = next(p for p in d.estimates().parameters if p.name == "inertia.J")
        assert j.value == pytest.approx(2e-4 * (1 + 0.5 * k), rel=0.05), name
