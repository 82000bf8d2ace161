"""The simulated drive as a python-can interface (``interface="canrls-sim"``)."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import time
from pathlib import Path

import can
import cantools
import numpy as np
import pytest
from cli_tool import python_module
from daemon_tool import reap

from canrls.can.decoder import Decoder
from canrls.can.e2e import e2e_crc
from canrls.can.frameblock import FrameBlock
from canrls.can.protocol import Protocol
from canrls.core.errors import ConfigError, EffectError
from canrls.sim import simulate

ROOT = Path(__file__).resolve().parents[2]
DBC = ROOT / "dbc" / "canrls.dbc"


def _drain(bus: can.BusABC, timeout: float = 0.2) -> list[can.Message]:
    out = []
    while (m := bus.recv(timeout)) is not None:
        out.append(m)
    return out


def test_frames_decode_with_cantools_and_e2e() -> None:
    db = cantools.database.load_file(str(DBC))
    with can.Bus(interface="canrls-sim", channel="standard", seed=1, realtime=False,
                 duration=0.5, start_time=0.0) as bus:
        msgs = _drain(bus)
    assert len(msgs) == 1000
    last: dict[int, int] = {}
    for m in msgs:
        assert m.arbitration_id in (0x101, 0x102) and m.dlc == 8 and not m.is_extended_id
        sig = db.decode_message(m.arbitration_id, m.data)  # raises outside the DBC
        assert sig["CRC"] == e2e_crc(m.arbitration_id, bytes(m.data))
        if m.arbitration_id in last:
            assert sig["Counter"] == (last[m.arbitration_id] + 1) % 16
        last[m.arbitration_id] = int(sig["Counter"])
    t = np.array([m.timestamp for m in msgs if m.arbitration_id == 0x101])
    assert np.allclose(np.diff(t), 1e-3) and t[0] == 0.0
    # the same drive as simulate() with the same settings, frame for frame
    ref = simulate("standard", seed=1, duration=0.5).frames
    got = FrameBlock.from_messages(msgs)
    assert np.array_equal(got.data, ref.data) and np.allclose(got.t, ref.t)


def test_realtime_frames_through_a_notifier() -> None:
    before = time.time()
    with can.Bus(interface="canrls-sim", channel="rt", seed=2) as bus:
        reader = can.BufferedReader()
        notifier = can.Notifier(bus, [reader])
        try:
            time.sleep(0.4)
        finally:
            notifier.stop()
        msgs = []
        while (m := reader.get_message(0.0)) is not None:
            msgs.append(m)
        now = time.time()
    # paced by the wall clock: 2 frames a millisecond (two feedback frames at 1 kHz) since
    # the drive's first period, none from the future. Counted against the time that did
    # pass, not the 0.4 s asked for: a loaded machine wakes this thread later (1199
    # frames were right after 0.6 s)
    assert len(msgs) >= 200
    assert before <= msgs[0].timestamp and all(m.timestamp <= now for m in msgs)
    assert len(msgs) <= 2 * (1000 * (now - msgs[0].timestamp) + 1)
    dec = Decoder(Protocol.load())
    dec.decode(FrameBlock.from_messages(msgs))
    assert dec.rejected.total == 0 and sum(dec.accepted.values()) == len(msgs)


def test_virtual_bus_pair() -> None:
    with can.Bus(interface="canrls-sim", channel="pair", realtime=False, duration=0.01) as sim, \
         can.Bus(interface="virtual", channel="pair") as virt:
        # the drive's frames reach a plain virtual bus on the channel
        drive = _drain(sim, 0.05)
        assert len(drive) == 20
        seen = _drain(virt, 0.05)
        assert [m.arbitration_id for m in seen] == [m.arbitration_id for m in drive]
        # frames sent by either side reach the other, not the sender
        virt.send(can.Message(arbitration_id=0x300, data=bytes(8), is_extended_id=False))
        got = sim.recv(1.0)
        assert got is not None and got.arbitration_id == 0x300
        sim.send(can.Message(arbitration_id=0x320, data=b"\x02" + bytes(7), is_extended_id=False))
        got = virt.recv(1.0)
        assert got is not None and got.arbitration_id == 0x320
        assert sim.recv(0.05) is None  # receive_own_messages=False


def test_buses_on_a_channel_share_one_drive() -> None:
    with can.Bus(interface="canrls-sim", channel="shared", seed=1, realtime=False,
                 duration=0.05) as a:
        with can.Bus(interface="canrls-sim", channel="shared") as b:  # joins, states nothing
            assert b.simulator is a.simulator
            from_a = _drain(a, 0.05)
            from_b = _drain(b, 0.05)
            assert len(from_a) == len(from_b) == 100
            assert [bytes(m.data) for m in from_a] == [bytes(m.data) for m in from_b]
            with pytest.raises(ConfigError, match="seed"):
                can.Bus(interface="canrls-sim", channel="shared", seed=5)
            with can.Bus(interface="canrls-sim", channel="shared", seed=1):  # same value: fine
                pass
    # the drive went with the last bus
    with can.Bus(interface="canrls-sim", channel="shared", seed=5, realtime=False) as c:
        assert c.scenario.seed == 5


def test_channel_names_the_scenario_and_string_kwargs() -> None:
    # as python -m can.logger --bus-kwargs passes them: strings
    with can.Bus(interface="canrls-sim", channel="linear:a", realtime="False", seed="3",
                 duration="0.01", params="coulomb.Tc=4.0", effects="inertia,coulomb") as bus:
        assert bus.scenario.truth.axis == "linear"
        assert bus.scenario.truth["coulomb.Tc"] == 4.0 and bus.scenario.seed == 3
        assert len(_drain(bus, 0.05)) == 20
    with pytest.raises(ConfigError, match="seed"):
        can.Bus(interface="canrls-sim", channel="bad", seed="x")
    with pytest.raises(EffectError, match="cogging"):
        can.Bus(interface="canrls-sim", channel="bad", effects="inertia,cogging")
    with pytest.raises(ConfigError, match="realtime"):
        can.Bus(interface="canrls-sim", channel="bad", realtime="maybe")


def test_faults_on_the_bus() -> None:
    with can.Bus(interface="canrls-sim", channel="faulty", realtime=False, duration=2.0, seed=4,
                 faults="drop=0.05,dup=0.01,silence=0.2s@1s") as bus:
        msgs = _drain(bus, 0.05)
        log = bus.fault_log
    assert len(msgs) == log.frames_out and log.frames_in == 4000 and log.silenced == 400
    dec = Decoder(Protocol.load())
    dec.decode(FrameBlock.from_messages(msgs))
    assert dec.rejected["repeated"] == log.duplicated
    assert sum(dec.lost.values()) == log.dropped + log.silenced


def test_detect_available_configs() -> None:
    found = can.detect_available_configs(interfaces=["canrls-sim"])
    assert {"interface": "canrls-sim", "channel": "standard"} in found


# --------------------------------------------------------------------------- other processes


@pytest.mark.slow
def test_python_can_logger_runs_against_it(tmp_path: Path) -> None:
    out = tmp_path / "sim.log"
    proc = subprocess.Popen(
        python_module("can.logger") + ["-i", "canrls-sim", "-c", "standard", "-f", str(out),
                     "--bus-kwargs", "realtime=False", "duration=0.2", "seed=1"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        assert proc.stdout is not None
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            if "Can Logger" in line or not line:
                break
        # the simulated 0.2 s (400 frames) come as fast as the simulator makes them (a cold
        # simulator compiles first): stop once the log has grown and then stayed the same
        # size for a second (the writer's buffer is flushed at the stop)
        size, still = -1, 0.0
        while time.monotonic() < deadline and still < 1.0:
            now = out.stat().st_size if out.exists() else 0
            still = still + 0.1 if now == size and now > 0 else 0.0
            size = now
            time.sleep(0.1)
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=30)
    finally:
        reap(proc)
    msgs = list(can.LogReader(str(out)))
    assert len(msgs) == 400
    assert {m.arbitration_id for m in msgs} == {0x101, 0x102}


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.mark.slow
def test_remote_over_loopback() -> None:
    pytest.importorskip("can_remote")
    port = _free_port()
    env = dict(os.environ)
    proc = subprocess.Popen(
        python_module("can_remote") + ["-i", "canrls-sim", "-c", "standard", "-H", "127.0.0.1",
                     "-p", str(port)],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
                break
            except OSError:
                if time.monotonic() > deadline or proc.poll() is not None:
                    pytest.fail("can_remote server did not start")
                time.sleep(0.1)
        with can.Bus(interface="remote", channel=f"ws://127.0.0.1:{port}/") as bus:
            msgs = [bus.recv(10.0) for _ in range(20)]
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    assert all(m is not None for m in msgs)
    dec = Decoder(Protocol.load())
    dec.decode(FrameBlock.from_messages([m for m in msgs if m is not None]))
    assert dec.rejected.total == 0


def test_a_machine_bus_hides_the_effects_it_is_given() -> None:
    """``hidden=`` of a machine: one effect per axis; a wrong count or one drive's
    ``hidden`` is refused with the key named."""
    from canrls.sim.interface import SimBus

    bus = SimBus(channel=f"hidden-{os.getpid()}", axes=3, hidden=",cogging:6,",
                 realtime=False, duration=1.0)
    try:
        assert bus._drive.config.hidden == ("", "cogging:6", "")
        assert [any(k.startswith("cogging:6.") for k in s.scenario.truth.params)
                for s in bus._drive.sims] == [False, True, False]
    finally:
        bus.shutdown()
    with pytest.raises(ConfigError, match="hidden: ',unbalance' gives 2 effects for 3 axes"):
        SimBus(channel=f"hidden2-{os.getpid()}", axes=3, hidden=",unbalance")
    with pytest.raises(ConfigError, match="canrls-sim: hidden: of a machine's drives"):
        SimBus(channel=f"hidden3-{os.getpid()}", hidden="unbalance")
