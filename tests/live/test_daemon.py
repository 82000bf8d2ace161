"""The daemon in one process on python-can's virtual bus (and the simulated drive)."""

from __future__ import annotations

import gc
import itertools
import json
import logging
import math
import os
import signal
import socket
import sys
import threading
import time
from pathlib import Path
from typing import Any

import can
import cantools
import numpy as np
import pytest
from can.interfaces.virtual import VirtualBus
from cli_tool import cli_error
from daemon_tool import DaemonTool, daemon_process, notify_socket

from canrls.can.estimator_frames import CommandCode, CommandResult, FrameDecoder, encode_command
from canrls.can.frameblock import FrameBlock
from canrls.can.logs import read_frames
from canrls.cli.main import main
from canrls.core.effect_names import EffectId
from canrls.core.errors import BusError, ConfigError
from canrls.live.bus_link import (
    RX_BATCH,
    BusLink,
    BusReader,
    FrameQueue,
    QueuedFrames,
    bus_config,
    messages_to_block,
    open_bus,
)
from canrls.live.daemon import Daemon
from canrls.live.daemon_settings import DaemonSettings
from canrls.live.publisher import Publisher
from canrls.live.sdnotify import SystemdNotifier
from canrls.processor import FrameProcessor
from canrls.processor.config import AppConfig

ROOT = Path(__file__).resolve().parents[2]
DBC = ROOT / "dbc" / "canrls.dbc"
BASE = ["inertia", "viscous", "coulomb"]
_ids = itertools.count()


def _chan(name: str) -> str:
    return f"test-daemon-{name}-{os.getpid()}-{next(_ids)}"


def _setup(effects: list[str] = BASE) -> tuple:
    cfg = AppConfig()
    cfg.model = {"effects": list(effects), "kt": 0.1}
    protocol = cfg.protocol()
    return protocol, cfg.model_for(protocol), cfg.settings()


def _sim(channel: str, effects: str = "inertia,viscous,coulomb", **kw: Any) -> dict[str, Any]:
    return dict(interface="canrls-sim", channel=channel, effects=effects, seed=3,
                excitation="slow", realtime=False, start_time=0.0, **kw)




# ------------------------------------------------------------------ end to end
def test_end_to_end_frames_decode_in_cantools(tmp_path: Path) -> None:
    protocol, model, settings = _setup()
    ch = _chan("e2e")
    tool = DaemonTool(ch)
    d = Daemon(protocol, model, settings,
               DaemonSettings(publish_interval=0.02, info_interval=0.2, commands=True),
               bus=_sim(ch),
               backpressure=True)
    try:
        d.start()
        assert d.wait_for(lambda x: x.pipeline.samples > 3000, 60)
        time.sleep(0.3)
        tool.command(encode_command(CommandCode.FREEZE))
        time.sleep(0.1)
    finally:
        d.stop()
        tool.take()
        tool.close()
    frames = tool.frames
    ids = {m.arbitration_id for m in frames}
    assert {0x300, 0x301, 0x302, 0x303, 0x310, 0x311, 0x312, 0x321} <= ids
    db = cantools.database.load_file(str(DBC))
    for m in frames:  # strict: raises on anything outside the DBC
        db.decode_message(m.arbitration_id, bytes(m.data), decode_choices=False)
    dec = FrameDecoder(units={p.name: p.unit for p in model.parameters})
    dec.feed_all(frames)
    names = [p.name for p in dec.table()]
    assert names == [p.name for p in model.parameters] and dec.count == 3
    final = d.parameter_reports()
    for got, want in zip(dec.table(), final, strict=True):
        assert got.unit == want.unit
        assert got.float_value == pytest.approx(want.float_value, rel=1e-6)
    assert dec.status is not None and dec.status.frozen
    assert dec.status.active_effects == model.active_effects
    assert dec.status.update_count > 0 and math.isfinite(dec.status.residual_rms)


def test_replayed_log_gives_bit_identical_parameters(tmp_path: Path) -> None:
    protocol, model, settings = _setup()
    ch = _chan("replay")
    log = tmp_path / "seen.log"
    d = Daemon(protocol, model, settings, DaemonSettings(record=log, block_interval=0.002),
               bus=_sim(ch, faults="drop=0.01,dup=0.005"), backpressure=True)
    try:
        d.start()
        assert d.wait_for(lambda x: x.pipeline.samples > 6000, 60)
    finally:
        d.stop()
    live = d.estimates()
    assert d.stats().blocks > 3
    for chunk in (997, 65536):
        proc = FrameProcessor(protocol, model, settings)
        for block in read_frames(log, chunk):
            proc.process(block)
        assert proc.frames == d.stats().frames
        off = proc.pipeline.estimates()
        for a, b in zip(live.parameters, off.parameters, strict=True):
            assert (a.name, a.value, a.sigma, a.fixed) == (b.name, b.value, b.sigma, b.fixed)
        assert off.residual_rms == live.residual_rms
        assert proc.rejected.total == d.processor.rejected.total


# ------------------------------------------------------------------ commands
def _cmd(code: int, effect: int = 0, order: int = 0, lam: float = 0.0) -> can.Message:
    return encode_command(code, effect, order, lam)


def _raw(data: bytes) -> can.Message:
    return can.Message(arbitration_id=0x320, is_extended_id=False, data=data)


def test_commands_good_and_bad() -> None:
    protocol, model, settings = _setup()
    ch = _chan("cmd")
    tool = DaemonTool(ch)
    d = Daemon(protocol, model, settings,
               DaemonSettings(publish_interval=1.0, commands=True, command_burst=100),
               bus={"interface": "virtual", "channel": ch})
    R = CommandResult
    try:
        d.start()

        def state() -> tuple:
            e = d.pipeline.estimators[0]
            return d.model.effect_names, d.pipeline.frozen, e.rls.lam, e.frls.state()["lam"]

        bad = [
            (_raw(b"\x01\x00\x00"), R.MALFORMED),
            (_raw(b""), R.MALFORMED),
            (_raw(bytes([9, 0, 0, 0, 0, 0, 0, 0])), R.UNKNOWN_COMMAND),
            (_cmd(CommandCode.ADD_EFFECT, 12), R.UNKNOWN_EFFECT),
            (_cmd(CommandCode.ADD_EFFECT, EffectId.COGGING, 0), R.BAD_VALUE),
            (_cmd(CommandCode.ADD_EFFECT, EffectId.OFFSET, 3), R.BAD_VALUE),
            (_raw(bytes([6, 0, 0, 0]) + np.float32(1.5).tobytes()), R.BAD_VALUE),
            (_cmd(CommandCode.SET_LAMBDA, lam=0.25), R.BAD_VALUE),
            (_cmd(CommandCode.ADD_EFFECT, EffectId.USER, 1), R.UNKNOWN_EFFECT),
            (_cmd(CommandCode.ADD_EFFECT, EffectId.INERTIA), R.NOT_APPLICABLE),
            (_cmd(CommandCode.REMOVE_EFFECT, EffectId.UNBALANCE), R.NOT_APPLICABLE),
            (_cmd(CommandCode.RESUME), R.NOT_APPLICABLE),
        ]
        before = state()
        for msg, want in bad:
            assert tool.command(msg) is want, (msg, want)
            assert state() == before  # a rejected command changes nothing
        assert d.stats().commands_rejected == len(bad)

        assert tool.command(_cmd(CommandCode.FREEZE)) is R.OK and d.pipeline.frozen
        assert tool.command(_cmd(CommandCode.FREEZE)) is R.NOT_APPLICABLE
        assert tool.command(_cmd(CommandCode.RESUME)) is R.OK and not d.pipeline.frozen
        assert tool.command(_cmd(CommandCode.SET_LAMBDA, lam=0.999)) is R.OK
        assert d.pipeline.estimators[0].rls.lam == pytest.approx(0.999)
        assert tool.command(_cmd(CommandCode.ADD_EFFECT, EffectId.COGGING, 6)) is R.OK
        assert d.model.effect_names == (*BASE, "cogging:6")
        assert tool.command(_cmd(CommandCode.REMOVE_EFFECT, EffectId.VISCOUS)) is R.OK
        assert d.model.effect_names == ("inertia", "coulomb", "cogging:6")
        assert tool.command(_cmd(CommandCode.RESET)) is R.OK
        # the parameter info follows the new model at once
        time.sleep(0.1)
        tool.take()
        dec = FrameDecoder()
        dec.feed_all(tool.frames)
        assert dec.count == 4
    finally:
        d.stop()
        tool.close()


def test_lambda_and_a_freeze_survive_an_added_effect_and_a_checkpoint() -> None:
    """A command's lambda and freeze live in the settings a changed model's pipeline
    is built from: an effect added after them keeps both, live and after a restore.
    Before, the pipeline for the new model was built from the configured lambda 1."""
    protocol, model, settings = _setup()
    ch = _chan("lam")
    tool = DaemonTool(ch)
    d = Daemon(protocol, model, settings,
               DaemonSettings(publish_interval=1.0, commands=True, command_burst=100),
               bus={"interface": "virtual", "channel": ch})
    R = CommandResult
    try:
        d.start()
        assert tool.command(_cmd(CommandCode.SET_LAMBDA, lam=0.99)) is R.OK
        assert tool.command(_cmd(CommandCode.FREEZE)) is R.OK
        assert tool.command(_cmd(CommandCode.ADD_EFFECT, EffectId.OFFSET)) is R.OK
        pipe = d.pipeline
        assert d.model.effect_names == (*BASE, "offset")
        assert pipe.frozen and pipe.settings.lam == pytest.approx(0.99)
        assert all(e.rls.lam == pytest.approx(0.99) and e.frls.lam == pytest.approx(0.99)
                   for e in pipe.estimators)
        state, running = d.processor.state(), d.model
    finally:
        d.stop()
        tool.close()
    # a checkpoint's state restored: the next added effect keeps them as well
    proc = FrameProcessor(protocol, model, settings, period=1e-3)
    proc.restore(state, running)
    assert proc.pipeline.frozen and proc.settings.lam == pytest.approx(0.99)
    pipe = proc.with_model(running.with_effects(add=["cogging:6"]))
    assert pipe.frozen and all(e.rls.lam == pytest.approx(0.99) for e in pipe.estimators)


def test_the_daemon_publishes_the_state_it_stops_in() -> None:
    """A freeze acknowledged just before a stop is in the last status published (and
    in ``canrls run --json``'s): the stop publishes once more after the last frames.
    Before, the last status was the last one of the grid, from before the freeze (here
    none at all)."""
    protocol, model, settings = _setup()
    ch = _chan("final")
    tool = DaemonTool(ch)
    d = Daemon(protocol, model, settings,
               DaemonSettings(publish_interval=30.0, commands=True),
               bus={"interface": "virtual", "channel": ch})
    try:
        d.start()  # no publication of the grid before the stop (30 s)
        assert tool.command(_cmd(CommandCode.FREEZE)) is CommandResult.OK
    finally:
        d.stop()
        tool.close()
    assert d.last_status is not None and "frozen" in d.last_status.flags


def test_commands_can_be_disabled() -> None:
    protocol, model, settings = _setup()
    ch = _chan("disabled")
    tool = DaemonTool(ch)
    d = Daemon(protocol, model, settings, DaemonSettings(commands=False, publish_interval=1.0),
               bus={"interface": "virtual", "channel": ch})
    try:
        d.start()
        for msg in (_cmd(CommandCode.RESET), _cmd(CommandCode.ADD_EFFECT, EffectId.OFFSET),
                    _cmd(CommandCode.FREEZE)):
            assert tool.command(msg) is CommandResult.DISABLED
        # whatever the frame holds (it was answered malformed, bad_value...)
        for raw in (b"\x01", b"", bytes([9, 0, 0, 0, 0, 0, 0, 0]),
                    bytes([6, 0, 0, 0]) + np.float32(1.5).tobytes()):
            assert tool.command(_raw(raw)) is CommandResult.DISABLED
        assert d.model.effect_names == tuple(BASE) and not d.pipeline.frozen
    finally:
        d.stop()
        tool.close()


def test_a_command_does_not_wait_for_the_block_interval() -> None:
    """Frames gather for block_interval (here the 3 s publish interval), but a command
    frame is taken at once: each of several commands back to back is acknowledged long
    before the interval."""
    protocol, model, settings = _setup()
    ch = _chan("hurry")
    tool = DaemonTool(ch)
    d = Daemon(protocol, model, settings, DaemonSettings(publish_interval=3.0, commands=True),
               bus={"interface": "virtual", "channel": ch})
    assert d.config.block_s == 3.0
    try:
        d.start()
        for code in (CommandCode.FREEZE, CommandCode.RESUME, CommandCode.FREEZE):
            t0 = time.monotonic()
            assert tool.command(_cmd(code)) is CommandResult.OK
            assert time.monotonic() - t0 < 1.0
        assert d.pipeline.frozen
    finally:
        d.stop()
        tool.close()


def test_a_backlog_is_taken_without_waiting_the_block_interval() -> None:
    """Frames gather for block_interval before a block, but when a whole block
    (``max_block`` frames) is already waiting, a backlog, the estimator takes it at once:
    it used to wait a block interval for each, so a backlog of N frames took
    N / max_block block intervals to work off (here 10 s for every 200 frames)."""
    protocol, model, settings = _setup()
    ch = _chan("backlog")
    d = Daemon(protocol, model, settings,
               DaemonSettings(publish_interval=10.0, max_block=200, queue_size=2000),
               bus=_sim(ch), backpressure=True)  # the drive as fast as it is taken
    assert d.config.block_s == 10.0
    try:
        d.start()
        assert d.wait_for(lambda x: x.stats().frames >= 4000, 30), d.stats().frames
    finally:
        d.stop()


def test_block_interval_follows_the_publish_interval() -> None:
    assert DaemonSettings().block_s == DaemonSettings().publish_interval == 0.1
    assert DaemonSettings(publish_interval=0.5).block_s == 0.5
    assert DaemonSettings(publish_interval=0.5, block_interval=0.01).block_s == 0.01
    assert DaemonSettings(publish_interval=0.0).block_s == 0.0
    assert DaemonSettings.from_table({"publish_interval": 0.2}).block_s == 0.2
    assert DaemonSettings.from_table({"block_interval": 0}).block_s == 0.0
    with pytest.raises(ConfigError, match="block_interval"):
        DaemonSettings.from_table({"block_interval": -1}, "f.toml")


def test_the_bus_reader_sleeps_a_quarter_block_at_most() -> None:
    assert DaemonSettings().rx_s == 0.005
    assert DaemonSettings(publish_interval=0.01).rx_s == 0.0025
    assert DaemonSettings(publish_interval=0.0).rx_s == 0.0  # latency: wake for each frame
    assert DaemonSettings(block_interval=0.0).rx_s == 0.0
    assert DaemonSettings(rx_interval=0.02).rx_s == 0.02
    assert DaemonSettings.from_table({"rx_interval": 0}).rx_s == 0.0
    with pytest.raises(ConfigError, match="daemon.rx_interval = -1"):
        DaemonSettings.from_table({"rx_interval": -1}, "f.toml")


class _CountingBus(VirtualBus):
    """A virtual bus that counts the reader's waits (``recv`` with a timeout) and
    takings (``recv(0)``)."""

    def __init__(self, **kw: Any) -> None:
        super().__init__(**kw)
        self.waits = 0
        self.takes = 0

    def recv(self, timeout: float | None = None) -> can.Message | None:
        if timeout:
            self.waits += 1
        else:
            self.takes += 1
        return super().recv(timeout)


def test_the_bus_reader_takes_every_frame_waiting_at_one_wake_up() -> None:
    """Frames already waiting are taken in one wake-up, in order."""
    ch = _chan("reader")
    stopping = threading.Event()
    q = FrameQueue(1000, False, stopping, lambda e: None)
    bus = _CountingBus(channel=ch)
    tx = VirtualBus(channel=ch)
    for i in range(50):
        tx.send(can.Message(arbitration_id=0x100, data=[i]))
    reader = BusReader(bus, q, 0.0)
    try:
        assert _received_within(q, 50, 5)
        assert q.take(100).data[:, 0].tolist() == list(range(50))
        assert bus.takes == 50  # 49 taken and one empty look
        assert bus.waits <= 2  # one for the 50 (perhaps the wait for the next one)
    finally:
        stopping.set()
        reader.stop()
        bus.shutdown()
        tx.shutdown()


def test_the_bus_reader_takes_a_virtual_bus_s_waiting_frames_in_one_go() -> None:
    """On python-can's own VirtualBus the frames waiting after the one ``recv`` are taken
    from its queue at once (:class:`QueuedFrames`), in order, none lost or repeated;
    with a batched reader as one block."""
    ch = _chan("reader-bulk")
    stopping = threading.Event()
    q = FrameQueue(1000, False, stopping, lambda e: None)
    blocks: list[int] = []
    on_block = q.on_block
    q.on_block = lambda b, *a: (blocks.append(len(b)), on_block(b, *a))  # type: ignore
    bus = VirtualBus(channel=ch)
    calls = []
    recv = bus.recv
    bus.recv = lambda timeout=None: (calls.append(timeout), recv(timeout))[1]  # type: ignore
    tx = VirtualBus(channel=ch)
    for i in range(300):
        tx.send(can.Message(arbitration_id=0x100 + i % 3, data=[i % 256, i // 256]))
    reader = BusReader(bus, q, 0.0, batched=True)
    try:
        assert _received_within(q, 300, 5)
        got = q.take(1000)
        assert (got.data[:, :2].astype(int) @ [1, 256]).tolist() == list(range(300))
        assert got.arbitration_id.tolist() == [0x100 + i % 3 for i in range(300)]
        assert blocks == [300]
        assert len(calls) <= 2  # the wait for the first frame (and for the next one)
    finally:
        stopping.set()
        reader.stop()
        bus.shutdown()
        tx.shutdown()


def test_queued_frames_only_for_python_can_s_own_virtual_bus() -> None:
    """The queue is read directly only where it holds exactly what ``recv`` returns:
    a subclass (it may make frames in ``recv``) and a bus with software filters keep
    ``recv``; a bounded queue is said to be (the reader must not sleep it full)."""
    ch = _chan("queued")
    buses = [VirtualBus(channel=ch), _CountingBus(channel=ch),
             VirtualBus(channel=ch, can_filters=[{"can_id": 1, "can_mask": 0x7FF}]),
             VirtualBus(channel=ch, rx_queue_size=5)]
    try:
        plain, sub, filtered, bounded = (QueuedFrames.of(b) for b in buses)
        assert sub is None and filtered is None
        assert plain is not None and not plain.bounded
        assert bounded is not None and bounded.bounded
        for i in range(5):
            buses[0].send(can.Message(arbitration_id=i))
        assert [m.arbitration_id for m in bounded.take(3)] == [0, 1, 2]
        assert [m.arbitration_id for m in bounded.take(10)] == [3, 4]
        assert bounded.take(10) == []
        buses[0].send(can.Message(arbitration_id=9), timeout=0)  # room again: no Full
    finally:
        for b in buses:
            b.shutdown()


def test_the_bus_reader_sleeps_on_an_unbounded_virtual_bus_however_fast() -> None:
    """An unbounded virtual queue drops nothing: the reader sleeps ``interval`` after
    every wake-up, fast bus or slow, and takes what gathered meanwhile at once."""
    ch = _chan("reader-unbounded")
    stopping = threading.Event()
    q = FrameQueue(10000, False, stopping, lambda e: None)
    bus = VirtualBus(channel=ch)
    tx = VirtualBus(channel=ch)
    reader = BusReader(bus, q, 2.0)
    try:
        for i in range(4 * RX_BATCH):  # a fast bus: far more than RX_BATCH in 2 s
            tx.send(can.Message(arbitration_id=0x100, data=[i % 256]))
        assert _received_within(q, 4 * RX_BATCH, 5)
        tx.send(can.Message(arbitration_id=0x100, data=[0]))
        assert not _received_within(q, 1 + 4 * RX_BATCH, 0.8)  # asleep all the same
        assert _received_within(q, 1 + 4 * RX_BATCH, 5)
    finally:
        stopping.set()
        reader.stop()
        bus.shutdown()
        tx.shutdown()


def _received_within(q: FrameQueue, n: int, seconds: float) -> bool:
    deadline = time.monotonic() + seconds
    while q.received < n and time.monotonic() < deadline:
        time.sleep(0.002)
    return q.received >= n


def test_the_bus_reader_sleeps_on_a_slow_bus_not_on_a_fast_one() -> None:
    """After a wake-up the reader sleeps ``interval`` while the bus brings fewer than
    RX_BATCH frames an interval (frames wait in the interface meanwhile); on a faster
    bus it goes back to recv at once, so the interface's buffer is not slept away."""
    ch = _chan("reader-sleep")
    stopping = threading.Event()
    q = FrameQueue(10000, False, stopping, lambda e: None)
    bus = VirtualBus(channel=ch, rx_queue_size=10000)  # a buffer that a sleep could fill
    tx = VirtualBus(channel=ch)
    reader = BusReader(bus, q, 2.0)
    try:
        time.sleep(0.3)  # a slow bus: one frame in 0.3 s
        tx.send(can.Message(arbitration_id=0x100, data=[0]))
        assert _received_within(q, 1, 5)
        tx.send(can.Message(arbitration_id=0x100, data=[1]))
        assert not _received_within(q, 2, 0.8)  # asleep: it waits in the interface
        assert _received_within(q, 2, 5)
        # a fast bus: 4 * RX_BATCH frames at once, far more than RX_BATCH in 2 s
        for i in range(4 * RX_BATCH):
            tx.send(can.Message(arbitration_id=0x100, data=[i % 256]))
        assert _received_within(q, 2 + 4 * RX_BATCH, 5)
        tx.send(can.Message(arbitration_id=0x100, data=[2]))
        assert _received_within(q, 3 + 4 * RX_BATCH, 0.8)  # no sleep after it
    finally:
        stopping.set()
        reader.stop()
        bus.shutdown()
        tx.shutdown()


def test_the_estimator_sleeps_until_a_publication_is_due() -> None:
    """The estimator sleeps until :meth:`Publisher.deadline`: a time at which a
    publication is due. The parameter info rides on the first publication of the grid
    at or after its own time; that time, falling between two publications (a
    publication a little late sets it), was a deadline too, already past: the estimator
    woke again and again with nothing to do, spinning until the next publication."""
    protocol, model, settings = _setup()
    cfg = DaemonSettings(publish_interval=0.1, info_interval=1.0)
    link = BusLink(FrameQueue(10, False, threading.Event(), lambda e: None),
                   lambda: VirtualBus(_chan("deadline")), cfg)  # never opened: sends nothing
    counters = {"frames_rejected": 0, "frames_lost": 0, "saturations": 0, "tx_dropped": 0}
    pub = Publisher(FrameProcessor(protocol, model, settings), cfg, link, lambda: counters)
    pub.start(100.0)
    pub.publish(100.1004)  # 0.4 ms late: carries the info, due again at 101.1004
    for k in range(2, 12):  # the grid, each 0.1 ms late; 101.1001 is before the info
        pub.publish(100.0 + 0.1 * k + 1e-4)
    assert pub.next_at == pytest.approx(101.2)
    for now in (101.1003, 101.1005, 101.15, 101.1999):  # the info's time passes
        deadline = pub.deadline(now)
        assert pub.due(deadline), (now, deadline)
        assert deadline > now  # a sleep, not a spin
    assert pub.due(101.2) and pub.deadline(101.2) == pytest.approx(101.2)
    pub.model_changed()  # a new model publishes at once
    assert pub.deadline(101.25) == 101.25 and pub.due(101.25)
    # publishing after every block: the info's time is a deadline (idle: every 0.25 s)
    pub0 = Publisher(pub.processor, DaemonSettings(publish_interval=0.0, info_interval=1.0),
                     link, lambda: counters)
    pub0.start(100.0)
    pub0.publish(100.0)
    assert pub0.deadline(100.9) == pytest.approx(101.0)
    assert pub0.deadline(100.5) == pytest.approx(100.75)


def _mean(xs: list[float]) -> float:
    xs = [x for x in xs if math.isfinite(x)]
    assert xs, "no finite residual RMS in the status frames of this window"
    return sum(xs) / len(xs)


def test_adding_the_missing_effect_makes_the_status_rms_fall() -> None:
    protocol, model, settings = _setup()
    ch = _chan("rms")
    tool = DaemonTool(ch)
    d = Daemon(protocol, model, settings, DaemonSettings(publish_interval=0.01, commands=True),
               bus=_sim(ch, effects="inertia,viscous,coulomb,unbalance"), backpressure=True)
    rms: list[tuple[int, float]] = []  # (frames processed, RlsStatus.ResidualRms)

    def sample(until: float, since: int) -> None:
        """Collect status frames until ``until`` s of frames, and at least 5 finite values
        after frame ``since`` (a loaded machine processes in larger blocks)."""
        end = time.monotonic() + 90

        def enough() -> bool:
            got = sum(1 for n, r in rms if n >= since and math.isfinite(r))
            return d.stats().frames >= until * 2000 and got >= 5

        while not enough() and time.monotonic() < end:
            for m in tool.take():
                if m.arbitration_id == 0x310:
                    rms.append((d.stats().frames, float(np.frombuffer(m.data[:4], "<f4")[0])))
            time.sleep(0.005)

    try:
        d.start()
        sample(12.0, 6 * 2000)
        assert tool.command(_cmd(CommandCode.ADD_EFFECT, EffectId.UNBALANCE)) is CommandResult.OK
        fix = d.stats().frames
        sample(24.0, fix + 6 * 2000)
    finally:
        d.stop()
        tool.close()
    before = _mean([r for n, r in rms if 6 * 2000 <= n <= fix])
    after = _mean([r for n, r in rms if n >= fix + 6 * 2000])
    assert after < 0.5 * before, (before, after)


# ------------------------------------------------------------------ bus faults
class _FlakyBus(VirtualBus):
    """A virtual bus whose send and recv can be made to fail."""

    send_fails = False
    recv_fails = False

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if type(self).send_fails:
            raise can.CanOperationError("transmit buffer full (test)")
        super().send(msg, timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if type(self).recv_fails:
            raise can.CanOperationError("network is down (test)")
        return super()._recv_internal(timeout)


def test_error_frames_pause_sending_and_recover(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, logger="canrls.live")
    protocol, model, settings = _setup()
    ch = _chan("errframes")
    tool = DaemonTool(ch)
    tool.bus.set_filters(None)
    d = Daemon(protocol, model, settings,
               DaemonSettings(publish_interval=0.01, fault_hold_s=0.5),
               bus={"interface": "virtual", "channel": ch})
    try:
        d.start()
        time.sleep(0.2)
        assert any(m.arbitration_id == 0x310 for m in tool.take())
        tool.bus.send(can.Message(is_error_frame=True, arbitration_id=0x40, data=bytes(8)))
        time.sleep(0.1)  # frames in flight
        tool.take()
        time.sleep(0.25)
        assert not [m for m in tool.take() if m.arbitration_id == 0x310]  # paused
        assert d.status().bus_fault and d.stats().tx_paused > 0
        time.sleep(0.5)
        resumed = [m for m in tool.take() if m.arbitration_id == 0x311]
        assert resumed and not resumed[-1].data[0] & 0x40  # BusFault cleared on the wire
        # the estimator thread alone ends the fault state, logged once
        assert [r.message for r in caplog.records].count(
            "CAN bus fault cleared: transmission resumed") == 1
        # bus-off ended at once by the controller's restart notification
        tool.bus.send(can.Message(is_error_frame=True, arbitration_id=0x40, data=bytes(8)))
        assert d.wait_for(lambda x: x.status().bus_fault, 2)
        tool.bus.send(can.Message(is_error_frame=True, arbitration_id=0x100, data=bytes(8)))
        assert d.wait_for(lambda x: not x.status().bus_fault, 0.4)
        assert d.stats().error_frames == 3
    finally:
        d.stop()
        tool.close()


def test_full_transmit_queue_drops_and_counts() -> None:
    protocol, model, settings = _setup()
    ch = _chan("txfull")

    class Bus(_FlakyBus):
        send_fails = True

    d = Daemon(protocol, model, settings, DaemonSettings(publish_interval=0.01),
               bus_factory=lambda: Bus(channel=ch))
    feeder = can.Bus(interface="canrls-sim", channel=ch, seed=1, realtime=False,
                     start_time=0.0, duration=2.0, excitation="slow")
    try:
        d.start()
        while feeder.recv(0) is not None:  # pump the drive's 2 s into the channel
            pass
        assert d.wait_for(lambda x: x.stats().frames >= 4000 and x.stats().tx_dropped > 50, 30)
        assert d.pipeline.samples > 1500  # the estimator was never held up
        assert not d.status().bus_fault  # a full queue is not a bus fault
    finally:
        d.stop()
        feeder.shutdown()
    # once stopped the count no longer moves: the status report's is the stats' (while
    # it ran, a drop between the two reads made them differ by one or two)
    assert d.status().tx_dropped == d.stats().tx_dropped


def test_vanished_interface_is_reopened_with_backoff() -> None:
    protocol, model, settings = _setup()
    ch = _chan("vanish")
    attempts: list[float] = []
    fail_opens = [0]

    class Bus(_FlakyBus):
        pass

    def factory() -> can.BusABC:
        attempts.append(time.monotonic())
        if fail_opens[0] > 0:
            fail_opens[0] -= 1
            raise BusError("cannot open CAN interface 'test' channel 'x': gone")
        return Bus(channel=ch)

    tool = DaemonTool(ch)
    d = Daemon(protocol, model, settings,
               DaemonSettings(publish_interval=0.02, reopen_min_s=0.05, reopen_max_s=0.2,
                              commands=True),
               bus_factory=factory)
    try:
        d.start()
        fail_opens[0] = 3
        Bus.recv_fails = True
        assert d.wait_for(lambda x: len(attempts) >= 3, 10)
        Bus.recv_fails = False
        assert d.wait_for(lambda x: x.stats().bus_reopens == 1, 10)
        gaps = np.diff(attempts[1:])
        assert gaps[0] >= 0.04 and all(g >= 0.04 for g in gaps)  # backoff, not a spin
        tool.take()
        time.sleep(0.2)
        assert any(m.arbitration_id == 0x310 for m in tool.take())  # publishing again
        # frames still reach the estimator through the new reader
        tool.bus.send(encode_command(CommandCode.FREEZE))
        assert d.wait_for(lambda x: x.pipeline.frozen, 5)
    finally:
        Bus.recv_fails = False
        d.stop()
        tool.close()


def test_the_supervisor_sleeps_until_the_bus_fails() -> None:
    """Without a watchdog the supervisor thread sleeps (it polled the bus's state 20 times
    a second: a wake-up costs CPU); a failing bus wakes it at once, and it reopens it."""
    protocol, model, settings = _setup()
    ch = _chan("sleep")
    opened: list[_FlakyBus] = []

    class Bus(_FlakyBus):
        pass

    def factory() -> can.BusABC:
        opened.append(Bus(channel=ch))
        return opened[-1]

    d = Daemon(protocol, model, settings, DaemonSettings(reopen_min_s=0.05),
               bus_factory=factory, notifier=SystemdNotifier(None, environ={}))
    assert d.sd.watchdog_interval is None
    looks: list[str] = []  # the supervisor's looks at the bus's state
    failed = d._link.failed
    is_set = failed.is_set

    def counted() -> bool:
        looks.append(threading.current_thread().name)
        return is_set()

    failed.is_set = counted  # type: ignore[method-assign]
    try:
        d.start()
        # the first look (at once), then one after the idle sleep of 1 s at most
        time.sleep(0.6)
        assert looks.count("canrls supervisor") <= 2, looks.count("canrls supervisor")
        Bus.recv_fails = True
        assert d.wait_for(lambda x: len(opened) >= 2, 10)  # reopened
        Bus.recv_fails = False
        assert d.wait_for(lambda x: x.stats().bus_reopens == 1, 10)
    finally:
        Bus.recv_fails = False
        d.stop()


# ------------------------------------------------------------------ configuration
def test_bus_config_ignores_python_can_config(monkeypatch: pytest.MonkeyPatch,
                                              tmp_path: Path) -> None:
    monkeypatch.setenv("CAN_INTERFACE", "socketcan")
    monkeypatch.setenv("CAN_CHANNEL", "can9")
    monkeypatch.setenv("CAN_BITRATE", "125000")
    monkeypatch.setenv("CAN_CONFIG", json.dumps({"receive_own_messages": True}))
    monkeypatch.setenv("HOME", str(tmp_path))
    (tmp_path / ".canrc").write_text("[default]\ninterface = socketcan\nchannel = can7\n")
    monkeypatch.setattr(can, "rc", {"interface": "socketcan", "channel": "can8"})
    cfg = AppConfig()
    with pytest.raises(ConfigError, match="no CAN interface"):
        bus_config(cfg)
    cfg.can = {"interface": "virtual", "channel": "cfg-chan", "bitrate": 500000}
    conf = bus_config(cfg)
    assert conf == {"interface": "virtual", "channel": "cfg-chan", "bitrate": 500000}
    with open_bus(conf) as bus:
        assert isinstance(bus, VirtualBus)
        assert bus.channel_id == "cfg-chan" and not bus.receive_own_messages
    cfg.can["bitrate"] = "fast"
    with pytest.raises(ConfigError, match="can.bitrate"):
        bus_config(cfg)
    with pytest.raises(BusError, match="nosuch"):
        open_bus({"interface": "socketcan_nosuch", "channel": "x"})


def test_daemon_settings_are_validated(tmp_path: Path) -> None:
    assert not DaemonSettings().commands  # off unless enabled
    s = DaemonSettings.from_table({"publish_interval": 0.5, "commands": False,
                                   "checkpoint": "state/cp.bin"}, "f.toml", tmp_path)
    assert s.publish_interval == 0.5 and not s.commands
    assert s.checkpoint == tmp_path / "state" / "cp.bin"
    for table, msg in (({"publish_rate": 1}, "unknown key"),
                       ({"commands": "yes"}, "true or false"),
                       ({"publish_interval": -1}, "publish_interval"),
                       ({"queue_size": 0}, "queue_size"),
                       ({"reopen_min_s": 5, "reopen_max_s": 1}, "reopen_max_s"),
                       ({"checkpoint": 3}, "file path"),
                       ({"max_parameters": 256}, "max_parameters = 256: must be in 1..255"),
                       ({"max_parameters": 0}, "max_parameters"),
                       ({"command_rate": 0}, "command_rate"),
                       ({"command_rate": "fast"}, "commands per second"),
                       ({"command_burst": 0.5}, "command_burst")):
        with pytest.raises(ConfigError, match=msg) as e:
            DaemonSettings.from_table(table, "f.toml")
        assert "f.toml" in str(e.value)


def test_the_obsolete_cache_dir_is_ignored_with_a_warning(
        caplog: pytest.LogCaptureFixture) -> None:
    """``[daemon] cache_dir`` (the directory of the compiled kernels' cache, when canrls
    compiled them at run time) still loads: ignored, with a warning naming the file and
    saying why; a configuration file of an earlier version keeps working."""
    with caplog.at_level(logging.WARNING, logger="canrls.live.daemon_settings"):
        s = DaemonSettings.from_table({"cache_dir": "kernels", "commands": True}, "f.toml")
    assert s.commands and not hasattr(s, "cache_dir")
    assert [r.getMessage() for r in caplog.records] == [
        "f.toml: daemon.cache_dir is obsolete and ignored (canrls compiles nothing at run "
        "time any more, so it keeps no cache of compiled kernels): remove it"]


def test_running_daemons_shorten_the_switch_interval_and_freeze_the_heap() -> None:
    protocol, model, settings = _setup()
    before = sys.getswitchinterval()
    assert gc.get_freeze_count() == 0
    a = Daemon(protocol, model, settings, DaemonSettings(switch_interval=0.0003),
               bus={"interface": "virtual", "channel": _chan("gil-a")})
    b = Daemon(protocol, model, settings, DaemonSettings(switch_interval=0.0003),
               bus={"interface": "virtual", "channel": _chan("gil-b")})
    a.start()
    try:
        assert sys.getswitchinterval() == pytest.approx(0.0003)
        assert gc.get_freeze_count() > 1000  # the imported modules, out of the collector's way
        b.start()
        a.stop()  # another daemon still runs: the settings stay
        assert sys.getswitchinterval() == pytest.approx(0.0003)
        assert gc.get_freeze_count() > 1000
    finally:
        a.stop()
        b.stop()
    assert sys.getswitchinterval() == before
    assert gc.get_freeze_count() == 0
    with pytest.raises(ConfigError, match="switch_interval"):
        DaemonSettings.from_table({"switch_interval": -1.0}, "f.toml")


def test_messages_to_block_matches_from_messages() -> None:
    msgs = [
        can.Message(timestamp=1.5, arbitration_id=0x101, data=bytes(range(8))),
        can.Message(timestamp=1.6, arbitration_id=0x1ABCDEF, is_extended_id=True, data=b"\x01"),
        can.Message(timestamp=1.7, arbitration_id=0x102, is_remote_frame=True, dlc=8),
        can.Message(timestamp=1.8, is_error_frame=True, arbitration_id=0x40, data=bytes(8)),
        can.Message(timestamp=1.9, arbitration_id=0x7FF, is_fd=True, data=bytes(range(12))),
    ]
    for sel in (msgs, msgs[:1], msgs[:4], []):
        a, b = messages_to_block(sel), FrameBlock.from_messages(sel)
        for f in ("t", "arbitration_id", "is_extended", "is_remote", "is_error", "dlc", "data"):
            assert np.array_equal(getattr(a, f), getattr(b, f)), f
            assert getattr(a, f).dtype == getattr(b, f).dtype, f


# ------------------------------------------------------------------ systemd, signals
def test_sd_notifydatagrams(tmp_path: Path) -> None:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    addr = str(tmp_path / "n.sock")
    sock.bind(addr)
    sock.settimeout(1.0)
    try:
        n = SystemdNotifier(environ={"NOTIFY_SOCKET": addr, "WATCHDOG_USEC": "2000000"})
        assert n.enabled and n.watchdog_interval == 2.0
        assert n.ready("up") and sock.recv(100) == b"READY=1\nSTATUS=up"
        assert n.watchdog() and sock.recv(100) == b"WATCHDOG=1"
        assert n.reloading() and sock.recv(100).startswith(b"RELOADING=1\nMONOTONIC_USEC=")
        n.close()
    finally:
        sock.close()
    off = SystemdNotifier(environ={})
    assert not off.enabled and not off.ready() and off.watchdog_interval is None
    other = SystemdNotifier(environ={"NOTIFY_SOCKET": "@x", "WATCHDOG_USEC": "5",
                                     "WATCHDOG_PID": "1"})
    assert other.watchdog_interval is None  # the watchdog is another process's
    missing = SystemdNotifier(environ={"NOTIFY_SOCKET": str(tmp_path / "none.sock")})
    assert missing.notify("READY=1") is False  # logged, never raised
    missing.close()


def test_sd_notify_never_waits_on_a_socket_nobody_reads(tmp_path: Path) -> None:
    """A full notification queue drops the message (it used to block the sender, the
    supervisor and the stop with it, once some ten datagrams were unread)."""
    sock, addr = notify_socket(tmp_path, "full")
    n = SystemdNotifier(environ={"NOTIFY_SOCKET": addr})
    results: list[bool] = []
    t = threading.Thread(target=lambda: results.extend(n.watchdog() for _ in range(2000)),
                         daemon=True)
    try:
        t.start()
        t.join(10)
        assert not t.is_alive() and len(results) == 2000
        assert results[0] and not results[-1]  # the first ones queued, then dropped
    finally:
        sock.close()  # unblocks a sender that waits (the old code)
        t.join(5)
        n.close()


@pytest.mark.slow
def test_sighup_reloads_model_and_sigterm_checkpoints(tmp_path: Path) -> None:
    conf = tmp_path / "canrls.toml"
    ckpt = tmp_path / "cp.bin"
    conf.write_text('[model]\neffects = ["inertia", "viscous", "coulomb"]\nkt = 0.1\n'
                    '[can]\ninterface = "canrls-sim"\nchannel = "sighup"\n'
                    f'[daemon]\ncheckpoint = "{ckpt.name}"\npublish_interval = 0.05\n')
    with daemon_process(["--log-level", "INFO", "run", "-C", str(conf), "--bus-kwargs",
                         "effects=inertia,viscous,coulomb,unbalance", "excitation=slow",
                         "seed=2", "--json"], tmp_path,
                        env={"WATCHDOG_USEC": "300000"}) as d:
        d.wait_ready()
        assert any("WATCHDOG=1" in g for g in d.notifications("WATCHDOG=1", 5))
        time.sleep(1.0)
        conf.write_text(conf.read_text().replace('"coulomb"]', '"coulomb", "unbalance"]'))
        d.send(signal.SIGHUP)
        got = d.notifications("READY=1", 10)
        assert any("RELOADING=1" in g for g in got) and "READY=1" in got[-1]
        time.sleep(1.0)
        out, err = d.stop(timeout=30)
    assert d.proc.returncode == 0, err
    res = json.loads(out)
    assert res["effects"] == [*BASE, "unbalance"]
    assert res["daemon"]["reloads"] == 1 and res["daemon"]["checkpoints"] >= 1
    assert "reload: model is now inertia,viscous,coulomb,unbalance" in err
    from canrls.live.checkpoint import load_checkpoint

    cp = load_checkpoint(ckpt)  # written at SIGTERM, after the last frame
    assert cp.model["effects"] == [*BASE, "unbalance"]
    assert cp.config_model["effects"] == [*BASE, "unbalance"]
    assert cp.state["pipeline"]["samples"] == res["daemon"]["samples"]


def test_a_term_outside_its_domain_is_logged_once_and_the_estimator_goes_on(
        caplog: pytest.LogCaptureFixture) -> None:
    from canrls.sim.scenario import Simulator, scenario

    caplog.set_level(logging.WARNING, logger="canrls.live")
    cfg = AppConfig()
    cfg.model = {"effects": ["inertia", "viscous", "coulomb", "user:root"], "kt": 0.1,
                 "terms": {"root": {"expr": "sqrt(omega)", "range": [0.0, 10.0]}}}
    protocol = cfg.protocol()
    d = Daemon(protocol, cfg.model_for(protocol), cfg.settings(), DaemonSettings(),
               bus={"interface": "virtual", "channel": _chan("nonfinite")})
    sim = Simulator(scenario("standard", effects="inertia,viscous,coulomb", seed=4,
                             duration=8.0, excitation="standard"), t0=0.0)
    for block in sim.frames(500):
        d.process(block.to_messages())
    assert not [r for r in caplog.records if "non-finite" in r.message]  # told when published
    d.publisher.publish(time.monotonic())
    est = d.pipeline.estimators[0]
    assert est.nonfinite_rows > 1000 and est.rls.count > 1000
    assert all(math.isfinite(p.value) for p in d.estimates().parameters)
    warned = [r for r in caplog.records if "non-finite term value" in r.message]
    assert len(warned) == 1 and "mechanical equation" in warned[0].message
    d.publisher.model_changed()  # the parameter info is due: the fit is looked at again
    d.publisher.publish(time.monotonic())
    assert len([r for r in caplog.records if "non-finite term value" in r.message]) == 1


@pytest.mark.parametrize(("own", "name"), [(768, "RlsEstimate"), (800, "RlsCommand")])
def test_canrls_run_refuses_a_drive_frame_on_an_id_of_canrls_unless_moved(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], own: int, name: str) -> None:
    """A drive DBC with the current on one of canrls' own IDs: canrls run would take its
    own publications (or a command) as feedback. One error line naming both frames, as
    export-c refuses it; with canrls' frames moved ([daemon] own_ids) it runs."""
    text = DBC.read_text()
    dbc = tmp_path / "drive.dbc"
    dbc.write_text(text[:text.index("BO_ 768 ")].replace("BO_ 257 DriveCurrent",
                                                         f"BO_ {own} DriveCurrent"))
    cfg = tmp_path / "drive.toml"
    cfg.write_text(f'[model]\neffects = ["inertia", "viscous", "coulomb"]\nkt = 0.1\n'
                   f'[can]\ndbc = "{dbc}"\n')
    args = ["run", "-i", "virtual", "-c", f"own-id-{os.getpid()}-{own}", "--config",
            str(cfg), "--duration", "0.2", "--json"]
    assert cli_error(capsys, args) == (
        f"error: the drive's {name} and the drive's feedback DriveCurrent would both be on "
        f"ID 0x{own:X}: give the drive's message another ID, or move canrls' frames with "
        f"[daemon] own_ids = \"offset:N\"")
    cfg.write_text(cfg.read_text() + '[daemon]\nown_ids = "offset:0x40"\n')
    assert main(args) == 0
    assert json.loads(capsys.readouterr().out)["daemon"]["frames"] == 0


def test_a_daemon_asked_for_the_target_path_without_one_says_so(
        caplog: pytest.LogCaptureFixture) -> None:
    """``fixed = "target"`` (the default) with no path given: the kernel's column is
    published, and a warning says so; asked for the kernel's column, nothing is said."""
    protocol, model, settings = _setup()
    bus = {"interface": "virtual", "channel": f"test-fixed-{os.getpid()}"}
    with caplog.at_level(logging.WARNING, logger="canrls.live.daemon"):
        Daemon(protocol, model, settings, DaemonSettings(fixed="kernel"), bus=bus).stop()
        assert not caplog.records
        Daemon(protocol, model, settings, DaemonSettings(), bus=bus).stop()
    assert [r.getMessage() for r in caplog.records] == [
        "daemon.fixed = 'target' but no target path was given (canrls.cli.run."
        "fixed_path_for builds it): the published fixed column is the kernel's on the "
        "float front end"]
