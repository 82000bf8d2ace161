"""The bulk receive of a SocketCAN bus (canrls._rx, canrls.live.socketcan) and the
daemon's block reader (canrls.live.bus_link.BlockReader).

This kernel has no AF_CAN: the SocketCAN socket is stood in by a UDP socket on
127.0.0.1 with ``SO_TIMESTAMPNS``, carrying the datagrams python-can's
``build_can_frame`` packs (16-byte ``struct can_frame``, 72-byte ``canfd_frame``), and
python-can's own ``SocketcanBus`` (its receive and send code unchanged) is built on it
without its constructor, which would open AF_CAN. The bulk path must give, field for
field, what python-can's ``recv`` and ``messages_to_block`` give for the same datagrams.
"""

from __future__ import annotations

import errno
import logging
import socket
import struct
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest
from can.bus import CanProtocol
from can.interfaces.socketcan import constants as sc
from can.interfaces.socketcan.socketcan import SocketcanBus, build_can_frame

from canrls.can.estimator_frames import CommandCode, encode_command
from canrls.can.frameblock import FrameBlock
from canrls.core.errors import ConfigError
from canrls.live.bus_link import RX_BATCH, BlockReader, BusLink, FrameQueue, messages_to_block
from canrls.live.daemon import Daemon
from canrls.live.daemon_settings import DaemonSettings
from canrls.live.socketcan import SocketcanReceiver, bulk_receiver, set_receive_buffer
from canrls.processor.config import AppConfig

LOOPBACK = "127.0.0.1"
HEADER = struct.Struct("=IBB1xB")


# ------------------------------------------------------------------ the stand-in
def _udp(peer: tuple[str, int] | None = None) -> socket.socket:
    """A UDP socket on 127.0.0.1 with python-can's SO_TIMESTAMPNS (as SocketcanBus sets it)."""
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.setsockopt(socket.SOL_SOCKET, sc.SO_TIMESTAMPNS, 1)
    s.bind((LOOPBACK, 0))
    if peer is not None:
        s.connect(peer)
    return s


def stand_in_bus(sock: socket.socket, channel: str = "vcan-stand-in",
                 fd: bool = True) -> SocketcanBus:
    """python-can's SocketcanBus on ``sock``: the attributes its constructor sets for one
    channel without filters (the kernel filter passes everything)."""
    bus = SocketcanBus.__new__(SocketcanBus)
    bus.socket = sock
    bus.channel = channel
    bus.channel_info = f"socketcan stand-in {channel}"
    bus._bcm_sockets = {}
    bus._is_filtered = True
    bus._task_id = 0
    bus._task_id_guard = threading.Lock()
    bus._can_protocol = CanProtocol.CAN_FD if fd else CanProtocol.CAN_20
    bus._periodic_tasks = []
    bus._filters = None
    bus._is_shutdown = False
    return bus


class _Peek:
    """A socket whose ``recvmsg`` peeks (MSG_PEEK): python-can reads the datagram the
    bulk path then takes, with the same kernel timestamp."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock

    def recvmsg(self, bufsize: int, ancbufsize: int = 0) -> Any:
        return self.sock.recvmsg(bufsize, ancbufsize, socket.MSG_PEEK)

    def fileno(self) -> int:
        return self.sock.fileno()


def peek_bus(sock: socket.socket) -> SocketcanBus:
    """python-can's SocketcanBus peeking at ``sock`` (the test closes ``sock`` itself)."""
    bus = stand_in_bus(_Peek(sock))  # type: ignore[arg-type]
    bus._is_shutdown = True  # nothing of its own to close
    return bus


def _raw(can_id: int, length: int, payload: bytes, size: int, flags: int = 0,
         len8_dlc: int = 0) -> bytes:
    """A datagram of ``size`` bytes: the can_frame header, then ``payload`` zero-padded."""
    return (HEADER.pack(can_id, length, flags, len8_dlc) + payload).ljust(size, b"\0")[:size]


def datagrams() -> list[bytes]:
    """Every kind of frame: standard and extended ids, remote and error frames, short and
    empty payloads, CAN FD with BRS/ESI and lengths between the FD steps, and datagrams
    python-can dissects by its own rules (len8_dlc, a length beyond the datagram,
    bytes after the length, a datagram neither 16 nor 72 bytes long)."""
    M = can.Message
    msgs = [
        M(arbitration_id=0x123, data=bytes(range(8)), is_extended_id=False),
        M(arbitration_id=0x1ABCDEF0, data=b"\x01\x02\x03", is_extended_id=True),
        M(arbitration_id=0x7FF, is_remote_frame=True, dlc=4, is_extended_id=False),
        M(arbitration_id=0x18FF00AA, is_remote_frame=True, dlc=8, is_extended_id=True),
        M(arbitration_id=0x40, is_error_frame=True, data=bytes(8), is_extended_id=False),
        M(arbitration_id=0x100 | 0x004, is_error_frame=True, data=b"\0\0\x08\0\0\0\0\0",
          is_extended_id=False),
        M(arbitration_id=0x200, data=b"", is_extended_id=False),
        M(arbitration_id=0x201, data=b"\xAA", is_extended_id=False),
        M(arbitration_id=0x320, data=b"\x02\0\0\0\0\0\0\0", is_extended_id=False),
        M(arbitration_id=0x300, data=bytes(range(12)), is_fd=True, bitrate_switch=True,
          is_extended_id=False),
        M(arbitration_id=0x1234567, data=bytes(range(64)), is_fd=True,
          error_state_indicator=True, is_extended_id=True),
        M(arbitration_id=0x301, data=b"\x05" * 5, is_fd=True, is_extended_id=False),
        M(arbitration_id=0x302, data=bytes(range(20)), is_fd=True, bitrate_switch=True,
          error_state_indicator=True, is_extended_id=False),
    ]
    out = [build_can_frame(m) for m in msgs]
    out += [
        _raw(0x10, 8, bytes(range(1, 9)), 16, len8_dlc=12),  # dlc 12, 8 bytes
        _raw(0x11, 12, bytes(range(1, 9)), 16),  # len 12 in a classic frame: 8 bytes
        _raw(0x12, 10, bytes(range(1, 65)), 72, flags=0x05),  # FD len 10 -> 12
        _raw(0x13, 3, b"\x01\x02\x03\xEE\xEE\xEE\xEE\xEE", 16, flags=0x03),  # after len
        _raw(0x14, 8, bytes(range(1, 9)), 12),  # 12 bytes: 4 of the 8
        _raw(0x15 | sc.CAN_EFF_FLAG | sc.CAN_RTR_FLAG | sc.CAN_ERR_FLAG, 0, b"", 16),
        _raw(0x20000001 | sc.CAN_EFF_FLAG, 64, bytes(range(64)), 72),
    ]
    return out


@pytest.fixture
def pair() -> Iterator[tuple[socket.socket, socket.socket]]:
    """(receiver, sender) on 127.0.0.1."""
    rx = _udp()
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tx.bind((LOOPBACK, 0))
    tx.connect(rx.getsockname())
    rx.connect(tx.getsockname())
    yield rx, tx
    rx.close()
    tx.close()


def _take(rx: SocketcanReceiver, n: int) -> tuple[FrameBlock, list[can.Message]]:
    """``n`` frames off ``rx`` (a few calls if they arrive in parts), with their messages."""
    blocks, msgs = [], []
    end = time.monotonic() + 10
    while sum(len(b) for b in blocks) < n and time.monotonic() < end:
        got = rx.recv(1.0)
        assert got.error is None
        blocks.append(got.block)
        msgs += rx.messages(got)
    return FrameBlock.concat(blocks), msgs


def _same(a: FrameBlock, b: FrameBlock, t: bool = True) -> None:
    for name in ("t", "arbitration_id", "is_extended", "is_remote", "is_error", "dlc",
                 "data"):
        if name == "t" and not t:
            continue
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape, name
        assert np.array_equal(x, y), name


# ------------------------------------------------------------------ the receive itself
def test_each_frame_equals_python_cans_recv_of_the_same_datagram(pair: Any) -> None:
    """Exactly, the timestamp included: python-can's ``recv`` peeks each datagram (the
    kernel's timestamp of that very datagram), then the bulk receive takes it."""
    rx_sock, tx = pair
    frames = datagrams()
    for f in frames:
        tx.send(f)
    ref_bus = peek_bus(rx_sock)
    rx = SocketcanReceiver(rx_sock, ref_bus.channel, capacity=1)
    for k in range(len(frames)):
        want = ref_bus.recv(5.0)
        assert want is not None
        got = rx.recv(5.0)
        assert got.error is None and len(got.block) == 1, k
        _same(got.block, messages_to_block([want]))
        (msg,) = rx.messages(got)
        assert msg.timestamp == want.timestamp, k
        assert msg.equals(want, timestamp_delta=None), (k, msg, want)
    assert len(rx.recv(0.0).block) == 0


#: how far apart two CPUs' clocks may stamp (the kernel stamps on the CPU that queues)
SKEW_S = 1e-3


def test_a_batch_equals_python_cans_recv_field_for_field() -> None:
    """The same datagrams to two sockets: one read in bulk (few recvmmsg calls), the other
    by python-can's ``SocketcanBus.recv``. Every field equal; the timestamps (each
    socket's own; exactly equal in the test above) in order, after the sending began."""
    a, b = _udp(), _udp()
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    bus = stand_in_bus(b)
    try:
        frames = datagrams() * 5  # within the default receive buffer (some 270)
        before = time.time()
        for f in frames:
            tx.sendto(f, a.getsockname())
            tx.sendto(f, b.getsockname())
        rx = SocketcanReceiver(a, bus.channel)
        block, msgs = _take(rx, len(frames))
        ref = [bus.recv(5.0) for _ in frames]
        assert all(m is not None for m in ref)
        want = messages_to_block(ref)  # type: ignore[arg-type]
        _same(block, want, t=False)
        assert all(x.equals(y, timestamp_delta=None) for x, y in zip(msgs, ref, strict=True))
        after = time.time()
        for t in (block.t, want.t):  # each socket's own receive times, in order (the
            # kernel may stamp the last ones after the sending returned, on a busy machine)
            # within the clock's skew between the CPUs that stamp them (a virtual machine
            # showed a datagram stamped microseconds before the one queued ahead of it)
            assert np.all(np.diff(t) >= -SKEW_S), np.diff(t).min()
            assert before - SKEW_S <= t.min() and t.max() <= after + SKEW_S
    finally:
        bus.shutdown()
        a.close()
        tx.close()


def test_more_frames_than_the_capacity_come_in_order_over_calls(pair: Any) -> None:
    rx_sock, tx = pair
    for i in range(10):
        tx.send(build_can_frame(can.Message(arbitration_id=0x100, data=[i])))
    rx = SocketcanReceiver(rx_sock, capacity=4)
    got = [rx.recv(5.0).block for _ in range(3)]
    assert [len(b) for b in got] == [4, 4, 2]
    assert FrameBlock.concat(got).data[:, 0].tolist() == list(range(10))


def test_an_empty_socket_gives_nothing_within_the_timeout(pair: Any) -> None:
    rx = SocketcanReceiver(pair[0])
    for timeout in (0.0, 0.05):
        got = rx.recv(timeout)
        assert len(got.block) == 0 and len(got.aux) == 0 and got.error is None


def test_a_closed_socket_raises_oserror(pair: Any) -> None:
    rx = SocketcanReceiver(pair[0])
    pair[0].close()
    with pytest.raises(OSError) as e:
        rx.recv(0.05)
    assert e.value.errno == errno.EBADF


def test_a_datagram_python_can_refuses_is_an_error_after_the_good_frames(pair: Any) -> None:
    """python-can's recv raises on it; the bulk receive delivers the frames around it and
    hands back the error to raise after them."""
    rx_sock, tx = pair
    good = build_can_frame(can.Message(arbitration_id=0x100, data=b"\x01"))
    bad = [b"\x01\x02\x03", _raw(0x101, 70, b"", 72)]  # too short; length byte above 64
    for f in (good, bad[0], good, bad[1], good):
        tx.send(f)
    ref = peek_bus(rx_sock)
    got = SocketcanReceiver(rx_sock).recv(5.0)
    assert len(got.block) == 3 and got.block.data[:, 0].tolist() == [1, 1, 1]
    assert isinstance(got.error, ValueError) and "shorter" in str(got.error)
    for f in bad:  # python-can refuses each of them too
        tx.send(f)
        with pytest.raises(Exception):  # noqa: B017 -- struct.error, ValueError
            ref.recv(5.0)
        rx_sock.recv(100)  # python-can only peeked it


# ------------------------------------------------------------------ the receive buffer
def test_the_receive_buffer_reaches_the_socket(caplog: pytest.LogCaptureFixture) -> None:
    s = _udp()
    try:
        caplog.set_level(logging.INFO, logger="canrls.live")
        before = s.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
        asked = 3 * 65536  # a size of its own, below net.core.rmem_max
        granted = set_receive_buffer(s, asked, "stand-in")
        now = s.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
        assert granted == now and now != before and now >= asked
        assert f"receive buffer {now} bytes (asked {asked})" in caplog.text
    finally:
        s.close()


class _Refusing(socket.socket):
    """A socket that refuses a receive buffer (a service without the right)."""

    def setsockopt(self, level: int, opt: int, value: Any, *rest: Any) -> None:  # type: ignore[override]
        if level == socket.SOL_SOCKET and opt in (socket.SO_RCVBUF, 33):
            raise PermissionError(errno.EPERM, "Operation not permitted")
        super().setsockopt(level, opt, value, *rest)


def test_a_refused_receive_buffer_is_a_warning_and_the_bus_runs(
        caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, logger="canrls.live")
    sock = _Refusing(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, sc.SO_TIMESTAMPNS, 1)
    sock.bind((LOOPBACK, 0))
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    stopping = threading.Event()
    q = FrameQueue(100, False, stopping, lambda e: None)
    link = BusLink(q, lambda: stand_in_bus(sock), DaemonSettings(rx_buffer=1 << 20))
    try:
        link.open()
        refused = [r for r in caplog.records if "refused" in r.message]
        assert len(refused) == 1 and refused[0].levelno == logging.WARNING
        assert "net.core.rmem_max" in refused[0].message
        tx.sendto(build_can_frame(can.Message(arbitration_id=0x100, data=[7])),
                  sock.getsockname())
        end = time.monotonic() + 5
        while q.received < 1 and time.monotonic() < end:
            time.sleep(0.005)
        assert q.take(10).data[:, 0].tolist() == [7]
    finally:
        stopping.set()
        link.close()
        tx.close()


# ------------------------------------------------------------------ the queue
def test_the_queue_counts_its_limit_in_frames_and_splits_blocks() -> None:
    stopping = threading.Event()
    q = FrameQueue(10, False, stopping, lambda e: None)
    blocks = [messages_to_block([can.Message(arbitration_id=0x100, data=[4 * k + i])
                                 for i in range(4)]) for k in range(3)]
    for b in blocks:
        q.on_block(b)
    assert q.received == 10 and q.overflow == 2 and q.held == 10
    assert not q.hurry.is_set()
    first = q.take(6)  # the second block split
    assert first.data[:, 0].tolist() == list(range(6)) and q.held == 4
    q.on_message_received(can.Message(arbitration_id=0x100, data=[99]))
    q.on_block(messages_to_block([can.Message(arbitration_id=0x320, data=[1],
                                              is_extended_id=False)]))
    assert q.hurry.is_set()  # a command frame waits
    rest = q.take(100)
    assert rest.data[:, 0].tolist() == [6, 7, 8, 9, 99, 1] and q.held == 0


def test_spans_of_the_receiver_queue_and_split_as_blocks(pair: Any) -> None:
    """The block reader queues what each receive took as it lies in the receiver's arena
    (a Span); ``take`` makes blocks of them, split at ``most``, commands counted."""
    rx_sock, tx = pair
    for i in range(10):
        tx.send(build_can_frame(can.Message(arbitration_id=0x320 if i == 7 else 0x100,
                                            data=[i], is_extended_id=False)))
    rx = SocketcanReceiver(rx_sock, capacity=4, command_id=0x320)
    q = FrameQueue(100, False, threading.Event(), lambda e: None)
    got = [rx.take(5.0) for _ in range(3)]
    assert [(len(s), c, e) for s, c, e in got] == [(4, 0, None), (4, 1, None), (2, 0, None)]
    q.on_block(got[0][0], got[0][1])
    assert not q.hurry.is_set()
    for span, commands, _ in got[1:]:
        q.on_block(span, commands)
    assert q.hurry.is_set() and q.held == 10
    first, rest = q.take(6), q.take(100)
    assert first.data[:, 0].tolist() == list(range(6))
    assert rest.data[:, 0].tolist() == [6, 7, 8, 9] and q.held == 0
    assert rest.arbitration_id.tolist() == [0x100, 0x320, 0x100, 0x100]


# ------------------------------------------------------------------ the daemon
def _wait(pred: Any, seconds: float = 30.0) -> bool:
    end = time.monotonic() + seconds
    while not pred() and time.monotonic() < end:
        time.sleep(0.01)
    return bool(pred())


def _feedback(n: int) -> list[can.Message]:
    from canrls.sim.scenario import Simulator, scenario

    sim = Simulator(scenario("standard", effects="inertia,viscous,coulomb", seed=5,
                             duration=n / 2000.0 + 0.1), t0=0.0)
    msgs: list[can.Message] = []
    for block in sim.frames(500):
        msgs += block.to_messages()
    return msgs[:n]


class _Peer:
    """The drive's side of the stand-in: sends frames to the daemon's socket, reads
    what the daemon sends (its parameter frames, acknowledgements)."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((LOOPBACK, 0))
        self.buses: list[SocketcanBus] = []
        self.seen: list[int] = []

    def factory(self) -> SocketcanBus:
        bus = stand_in_bus(_udp(self.sock.getsockname()))
        self.buses.append(bus)
        return bus

    def send(self, msgs: list[can.Message]) -> None:
        """At the drive's pace, two frames a millisecond (the daemon checks the period
        the receive timestamps give against the DBC's)."""
        dest = self.buses[-1].socket.getsockname()
        t0 = time.perf_counter()
        for i in range(0, len(msgs), 2):
            for m in msgs[i:i + 2]:
                self.sock.sendto(build_can_frame(m), dest)
            wait = t0 + (i // 2 + 1) * 1e-3 - time.perf_counter()
            if wait > 0:
                time.sleep(wait)

    def read(self) -> None:
        """The frames waiting (the daemon publishes all the while: no waiting for a
        quiet moment)."""
        while True:
            try:
                f = self.sock.recv(100, socket.MSG_DONTWAIT)
            except BlockingIOError:
                return
            self.seen.append(HEADER.unpack_from(f)[0] & 0x7FF)

    def close(self) -> None:
        self.sock.close()


def _daemon(peer: _Peer, **kw: Any) -> Daemon:
    cfg = AppConfig()
    cfg.model = {"effects": ["inertia", "viscous", "coulomb"], "kt": 0.1}
    protocol = cfg.protocol()
    return Daemon(protocol, cfg.model_for(protocol), cfg.settings(),
                  DaemonSettings(publish_interval=0.02, **kw), bus_factory=peer.factory)


def test_the_daemon_reads_a_socketcan_bus_in_blocks(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """Feedback, an error frame and a command through the block reader: every frame
    processed, the error frame counted, the command answered, the recorder given
    python-can's messages; the socket closed under it: a bus failure, reopened."""
    caplog.set_level(logging.DEBUG, logger="canrls.live.bus_link")
    peer = _Peer()
    rec = tmp_path / "seen.log"
    d = _daemon(peer, commands=True, record=rec)
    feedback = _feedback(4000)
    try:
        d.start()
        assert "read by BlockReader" in caplog.text
        peer.send(feedback[:2000])
        peer.read()  # room in its socket for the acknowledgement
        peer.send([can.Message(arbitration_id=0x320, is_extended_id=False,
                               data=encode_command(CommandCode.FREEZE).data)])
        assert _wait(lambda: d.stats().commands >= 1)
        time.sleep(0.1)
        peer.read()  # the acknowledgement, before the error frame pauses transmission
        peer.send([can.Message(arbitration_id=0x40, is_error_frame=True, data=bytes(8),
                               is_extended_id=False)])
        assert _wait(lambda: d.stats().frames >= 2002)
        peer.buses[-1].socket.close()  # the interface vanishes
        assert _wait(lambda: d.stats().bus_reopens >= 1 and len(peer.buses) == 2)
        peer.send(feedback[2000:])
        assert _wait(lambda: d.stats().frames >= 4002)
        time.sleep(0.1)
        peer.read()
    finally:
        d.stop()
        peer.close()
    s = d.stats()
    assert s.frames == 4002 and s.error_frames == 1 and s.rx_overflow == 0
    assert s.commands == 1 and 0x321 in peer.seen and 0x300 in peer.seen
    assert s.listener_cpu_s > 0.0
    logged = list(can.LogReader(str(rec)))
    assert len(logged) == 4002
    want = [*feedback[:2000], None, None, *feedback[2000:]]
    for got, m in zip(logged, want, strict=True):
        if m is not None:
            assert got.arbitration_id == m.arbitration_id and got.data == m.data


def test_rx_bulk_false_reads_a_socketcan_bus_through_python_can(
        caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.DEBUG, logger="canrls.live.bus_link")
    peer = _Peer()
    d = _daemon(peer, rx_bulk=False)
    try:
        d.start()
        assert "read by BusReader" in caplog.text
        peer.send(_feedback(500))
        assert _wait(lambda: d.stats().frames >= 500)
    finally:
        d.stop()
        peer.close()
    assert d.stats().frames == 500


def test_other_buses_are_not_read_in_bulk() -> None:
    bus = can.Bus(interface="virtual", channel="test-socketcan-rx-virtual", ignore_config=True)
    try:
        assert bulk_receiver(bus) is None
    finally:
        bus.shutdown()
    sock = _udp()
    filtered = stand_in_bus(sock)
    try:
        assert isinstance(bulk_receiver(filtered), SocketcanReceiver)
        filtered._filters = [{"can_id": 0x100, "can_mask": 0x7FF}]
        filtered._is_filtered = False  # python-can filters in software: its recv
        assert bulk_receiver(filtered) is None
    finally:
        filtered.shutdown()


@pytest.mark.parametrize("table, key", [({"rx_bulk": 1}, "rx_bulk"),
                                        ({"rx_buffer": -1}, "rx_buffer"),
                                        ({"rx_buffer": 1.5}, "rx_buffer")])
def test_the_rx_settings_are_checked(table: dict[str, Any], key: str) -> None:
    with pytest.raises(ConfigError, match=f"daemon.{key}"):
        DaemonSettings.from_table(table, "x.toml")
    assert DaemonSettings.from_table({"rx_bulk": False, "rx_buffer": 0}).rx_bulk is False


def _received_within(q: FrameQueue, n: int, seconds: float) -> bool:
    return _wait(lambda: q.received >= n, seconds)


def test_the_block_reader_sleeps_on_a_slow_bus_not_on_a_fast_one(pair: Any) -> None:
    """BusReader's rule (RX_BATCH): after a wake-up it sleeps ``interval`` while the bus
    brings fewer than RX_BATCH frames an interval; on a faster bus it does not."""
    rx_sock, tx = pair
    stopping = threading.Event()
    q = FrameQueue(10000, False, stopping, lambda e: None)
    reader = BlockReader(SocketcanReceiver(rx_sock), q, 2.0)

    def send(*data: int) -> None:
        for i in data:
            tx.send(build_can_frame(can.Message(arbitration_id=0x100, data=[i % 256])))

    try:
        time.sleep(0.3)  # a slow bus: one frame in 0.3 s
        send(0)
        assert _received_within(q, 1, 5)
        send(1)
        assert not _received_within(q, 2, 0.8)  # asleep: it waits in the socket
        assert _received_within(q, 2, 5)
        send(*range(4 * RX_BATCH))  # a fast bus: 4 * RX_BATCH frames at once
        assert _received_within(q, 2 + 4 * RX_BATCH, 5)
        send(2)
        assert _received_within(q, 3 + 4 * RX_BATCH, 0.8)  # no sleep after it
        assert q.take(10000).data[:, 0].tolist() == [0, 1, *range(4 * RX_BATCH), 2]
    finally:
        stopping.set()
        reader.stop()
