"""The daemon's side of the CAN bus: opening it, frames in, frames out, faults.

::

    bus --BusReader--> FrameQueue (a Listener: queues, nothing more)
        (SocketCAN:         | take(): a FrameBlock
         BlockReader)
    BusLink: opens the bus (and its reader), reopens it with backoff when recv
             raises, sends without blocking, pauses transmission on error frames;
             an axis of a machine: on the machine's one bus (SharedBus,
             canrls.live.hub) instead of its own

The bus is opened from the ``[can]`` table and the command line only
(``ignore_config=True``). The batched and bulk readers, the fault handling and their
settings: docs/daemon.md.
"""

from __future__ import annotations

import collections
import logging
import queue
import socket
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any, Protocol

import can
import numpy as np
from can.interfaces.virtual import VirtualBus

from canrls.can.estimator_frames import frame_ids
from canrls.can.frameblock import FrameBlock
from canrls.core.errors import BusError, ConfigError
from canrls.live.daemon_settings import DaemonSettings
from canrls.live.journal import JOURNAL
from canrls.live.socketcan import (
    SocketcanReceiver,
    Span,
    bulk_receiver,
    set_receive_buffer,
    socketcan_socket,
    to_block,
)
from canrls.processor.config import AppConfig

__all__ = ["BlockReader", "BusLink", "BusReader", "FrameQueue", "QueuedFrames", "RX_BATCH",
           "SharedBus", "bus_config", "command_rows", "is_command", "messages_to_block",
           "open_bus", "shutdown_bus", "COMMAND_ID", "command_id"]

log = logging.getLogger(__name__)

#: Arbitration ID of ``RlsCommand`` in the default DBC.
COMMAND_ID = frame_ids().command


def command_id(own_offset: int) -> int:
    """The ``RlsCommand`` ID of an axis whose own frames are moved by ``own_offset``
    (``[daemon] own_ids``): where its daemon listens and its monitor sends."""
    return COMMAND_ID + own_offset

# SocketCAN error classes (linux/can/error.h) in an error frame's arbitration ID
_CAN_ERR_BUSOFF = 0x40
_CAN_ERR_RESTARTED = 0x100
_BUS_KEYS = ("interface", "channel", "bitrate", "fd", "data_bitrate")


def bus_config(cfg: AppConfig | None = None) -> dict[str, Any]:
    """Every argument of the bus, explicitly: ``[can]`` overridden by the command line's
    bus arguments (:attr:`AppConfig.bus <canrls.processor.config.AppConfig.bus>`).

    :raises ConfigError: no interface, or a value of the wrong type.
    """
    conf: dict[str, Any] = {}
    src = cfg.source if cfg is not None else "<command line>"
    if cfg is not None:
        for k in _BUS_KEYS:
            if k in cfg.can:
                conf[k] = cfg.can[k]
        conf.update(cfg.bus)
    if not conf.get("interface"):
        raise ConfigError(f"{src}: no CAN interface: set can.interface in the configuration or "
                          f"-i/--interface (socketcan, virtual, canrls-sim, remote, ...)")
    if not isinstance(conf["interface"], str):
        raise ConfigError(f"{src}: can.interface = {conf['interface']!r}: must be a string")
    for k in ("bitrate", "data_bitrate"):
        v = conf.get(k)
        if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v <= 0):
            raise ConfigError(f"{src}: can.{k} = {v!r}: must be a positive integer (bit/s)")
    if "fd" in conf and not isinstance(conf["fd"], bool):
        raise ConfigError(f"{src}: can.fd = {conf['fd']!r}: must be true or false")
    return conf


def open_bus(config: Mapping[str, Any]) -> can.BusABC:
    """``can.Bus(**config, ignore_config=True)``: python-can's config files and
    environment variables are not consulted.

    :raises BusError: the interface cannot be opened (names interface and channel).
    """
    conf = dict(config)
    try:
        return can.Bus(ignore_config=True, **conf)
    except (can.CanError, OSError, ValueError, ImportError, TypeError, NotImplementedError) as e:
        raise BusError(f"cannot open CAN interface {conf.get('interface')!r} channel "
                       f"{conf.get('channel')!r}: {e}") from e


def shutdown_bus(bus: can.BusABC) -> None:
    """Shut ``bus`` down. An interface whose shutdown fails (the connection of a lost
    python-can-remote bus: ``ENOTCONN``) is marked shut down all the same and its socket
    closed: otherwise python-can's ``BusABC.__del__`` tries again when the object is
    collected and prints a raw "Exception ignored" traceback at exit."""
    try:
        bus.shutdown()
    except Exception as e:  # noqa: BLE001 -- any interface's failure: the bus is gone
        log.debug("bus shutdown: %s: %s", type(e).__name__, e)
        can.BusABC.shutdown(bus)  # the base's part: marked shut down, periodic tasks off
        sock = getattr(bus, "socket", None)
        if isinstance(sock, socket.socket):
            sock.close()


def messages_to_block(msgs: Sequence[can.Message]) -> FrameBlock:
    """:meth:`FrameBlock.from_messages`, vectorised (the same block, field for field)."""
    n = len(msgs)
    if n == 0:
        return FrameBlock.empty()
    datas = [m.data for m in msgs]
    lens = [len(d) for d in datas]
    width = max(8, max(lens))
    if min(lens) == width:
        data = np.frombuffer(b"".join(datas), np.uint8).reshape(n, width).copy()
    else:
        data = np.frombuffer(b"".join(bytes(d).ljust(width, b"\0") for d in datas),
                             np.uint8).reshape(n, width).copy()
    return FrameBlock(
        t=np.array([m.timestamp for m in msgs], np.float64),
        arbitration_id=np.array([m.arbitration_id for m in msgs], np.uint32),
        is_extended=np.array([m.is_extended_id for m in msgs], np.bool_),
        is_remote=np.array([m.is_remote_frame for m in msgs], np.bool_),
        is_error=np.array([m.is_error_frame for m in msgs], np.bool_),
        dlc=np.array(lens, np.uint8),
        data=data,
    )


def is_command(msg: can.Message, command_id: int = COMMAND_ID) -> bool:
    """``msg`` is an ``RlsCommand`` frame (on ``command_id``: an axis's own)."""
    return msg.arbitration_id == command_id and not msg.is_extended_id


def command_rows(block: FrameBlock, command_id: int = COMMAND_ID) -> np.ndarray:
    """Mask of the ``RlsCommand`` frames of ``block`` (:func:`is_command` of each row)."""
    return (block.arbitration_id == command_id) & ~block.is_extended


def moved(msg: can.Message, offset: int) -> can.Message:
    """A copy of ``msg`` whose ID is ``offset`` further (an axis's own frames)."""
    return can.Message(timestamp=msg.timestamp, arbitration_id=msg.arbitration_id + offset,
                       is_extended_id=msg.is_extended_id, is_remote_frame=msg.is_remote_frame,
                       dlc=msg.dlc, data=msg.data, is_fd=msg.is_fd,
                       bitrate_switch=msg.bitrate_switch, channel=msg.channel)


class FrameQueue(can.Listener):
    """Runs in the reader's thread: queues each frame, nothing more.

    The :class:`BusReader` hands it frames one by one (:meth:`on_message_received`), the
    :class:`BlockReader` of a SocketCAN bus whole blocks (:meth:`on_block`); the
    estimator takes a :class:`~canrls.can.frameblock.FrameBlock` of either (:meth:`take`).

    :param limit: frames held; beyond, a frame is dropped and counted in
        :attr:`overflow` (or, with ``block``, the reader's thread waits for room).
    :param stopping: set when the daemon stops (a waiting reader gives up).
    :param on_error: called with the exception when the bus's ``recv`` raises.
    :param full: frames that make a whole block (the daemon's ``max_block``): once that
        many are queued the estimator is hurried too (0: never); a backlog is not left
        to gather for a block interval.
    """

    def __init__(self, limit: int, block: bool, stopping: threading.Event,
                 on_error: Callable[[BaseException], None], full: int = 0) -> None:
        #: frames (python-can's reader) or pieces of frames (the bulk reader), oldest first
        self.queue: collections.deque[can.Message | FrameBlock | Span] = collections.deque()
        #: set when a frame is queued
        self.wake = threading.Event()
        #: set when a command frame is queued, a whole block waits (``full``) or the
        #: input closes: the estimator stops letting frames gather and takes them at once
        self.hurry = threading.Event()
        self.full = full if full > 0 else 1 << 62
        #: the ID of the command frames that hurry the estimator (an axis's own)
        self.command_id = COMMAND_ID
        #: (ID, extended) of the only frames queued, error frames aside (None: every
        #: frame); a SocketCAN bus filters in the kernel instead (:class:`BusLink`)
        self.accept: frozenset[tuple[int, bool]] | None = None
        self.space = threading.Event()
        self.limit = limit
        self.block = block
        #: frames queued (the reader's thread counts them) and taken (the estimator's)
        self.received = 0
        self.taken = 0
        self.overflow = 0
        #: gets every frame too (``[daemon] record``)
        self.recorder: can.Listener | None = None
        self._stopping = stopping
        self._on_error = on_error
        self._cpu0: float | None = None
        #: thread CPU time of the reader's thread since the first frame [s]
        self.cpu = 0.0
        #: whether :attr:`cpu` is kept (False: a machine's one reader feeds this queue
        #: and keeps its own, :class:`canrls.live.hub.BusHub`)
        self.clock_cpu = True
        #: open while set (:meth:`hold`)
        self.gate = threading.Event()
        self.gate.set()

    def on_message_received(self, msg: can.Message) -> None:
        accept = self.accept
        if accept is not None and not msg.is_error_frame and (
                msg.arbitration_id, msg.is_extended_id) not in accept:
            return  # another axis's frame: never queued
        while not self.gate.is_set() and not self._stopping.is_set():
            self.gate.wait(0.05)
        q = self.queue
        if self.received - self.taken >= self.limit:
            if not self.block:
                self.overflow += 1
                return
            while self.received - self.taken >= self.limit and not self._stopping.is_set():
                self.space.clear()
                self.space.wait(0.05)
        q.append(msg)
        if is_command(msg, self.command_id) or self.received + 1 - self.taken >= self.full:
            self.hurry.set()
        if self.recorder is not None:
            self.recorder.on_message_received(msg)
        self.received += 1
        self._queued(self.received & 255 == 1)

    def on_block(self, block: FrameBlock | Span, commands: int | None = None,
                 messages: Callable[[Span, int], list[can.Message]] | None = None) -> None:
        """Queue frames in one piece (the :class:`BlockReader`'s thread: a
        :class:`~canrls.live.socketcan.Span` of its receiver, or a block), as
        :meth:`on_message_received` each of them: the gate, the limit in frames (the
        newest beyond it dropped and counted), a command frame hurries the estimator.

        :param commands: command frames among them (None: looked for in the block).
        :param messages: ``messages(span, n)``: its first ``n`` frames as python-can's
            messages, called only when a recorder is set.
        """
        while not self.gate.is_set() and not self._stopping.is_set():
            self.gate.wait(0.05)
        n = len(block)
        if self.received - self.taken + n > self.limit:
            if not self.block:
                keep = max(0, self.limit - (self.received - self.taken))
                self.overflow += n - keep
                if keep == 0:
                    return
                n = keep
                block = (block.head(keep) if isinstance(block, Span)
                         else block.take(slice(0, keep)))
            else:  # room for the whole block (or an empty queue: a block above the limit)
                while (self.received - self.taken + n > self.limit
                       and self.received > self.taken and not self._stopping.is_set()):
                    self.space.clear()
                    self.space.wait(0.05)
        self.queue.append(block)
        if commands is None:
            commands = int(command_rows(to_block([block]) if isinstance(block, Span)
                                        else block, self.command_id).any())
        if commands or self.received + n - self.taken >= self.full:
            self.hurry.set()
        if self.recorder is not None and messages is not None and isinstance(block, Span):
            for m in messages(block, n):
                self.recorder.on_message_received(m)
        self.received += n
        self._queued(self.clock_cpu)

    def _queued(self, clock: bool) -> None:
        """After frames were queued: the reader's CPU time (when ``clock``: its clock is
        read every 256 frames one by one, at every block), and the estimator woken."""
        if clock:
            now = time.thread_time()
            if self._cpu0 is None:
                self._cpu0 = now
            self.cpu = now - self._cpu0
        if not self.wake.is_set():
            self.wake.set()

    def on_error(self, exc: Exception) -> None:
        self.report(exc)
        time.sleep(0.05)  # the reader retries recv at once: do not spin

    def report(self, exc: BaseException) -> None:
        """The bus's ``recv`` raised: tell the daemon (a shared reader tells every axis)."""
        self._on_error(exc)

    def stop(self) -> None:
        """The reader stops (bus reopened or daemon stopping): the queue stays."""

    def hold(self, hold: bool) -> None:
        """Close (``True``) or open the gate: while closed the reader's thread waits."""
        if hold:
            self.gate.clear()
        else:
            self.gate.set()

    @property
    def held(self) -> int:
        """Frames in the queue."""
        return max(0, self.received - self.taken)

    def take(self, most: int) -> FrameBlock:
        """Up to ``most`` frames, oldest first, off the queue: one block (a queued piece
        is split at ``most``)."""
        q = self.queue
        parts: list[FrameBlock] = []
        msgs: list[can.Message] = []
        spans: list[Span] = []
        k = 0
        while q and k < most:
            item = q[0]
            if isinstance(item, can.Message):
                if spans:
                    parts.append(to_block(spans))
                    spans = []
                q.popleft()  # item
                msgs.append(item)
                k += 1
                continue
            if msgs:
                parts.append(messages_to_block(msgs))
                msgs = []
            room = most - k
            if isinstance(item, Span):
                if len(item) > room:
                    spans.append(item.head(room))
                    q[0] = item.tail(room)
                    k = most
                    break
                q.popleft()  # item
                spans.append(item)
                k += len(item)
                continue
            if spans:
                parts.append(to_block(spans))
                spans = []
            if len(item) > room:
                parts.append(item.take(slice(0, room)))
                q[0] = item.take(slice(room, None))
                k = most
                break
            q.popleft()  # item
            parts.append(item)
            k += len(item)
        if msgs:
            parts.append(messages_to_block(msgs))
        if spans:
            parts.append(to_block(spans))
        self.taken += k
        self.space.set()
        if len(parts) == 1:
            return parts[0]
        return FrameBlock.concat(parts)

    def wake_all(self) -> None:
        """Wake a waiting estimator and a waiting reader (stopping)."""
        self.space.set()
        self.hurry.set()
        self.wake.set()


#: the reader sleeps ``rx_interval`` after a wake-up while the bus brings fewer frames
#: than this in an interval (measured since the last wake-up); on a faster bus it does
#: not sleep: wake-ups fill by themselves, and a sleep would use up the interface's
#: buffer (a SocketCAN socket's default holds some 270 frames)
RX_BATCH = 64
#: most frames a batched :class:`BusReader` hands on in one block
RX_BATCH_MAX = 4096


class _Reader:
    """The reader's thread, started at once: :meth:`_run` (the subclass's loop) until
    :meth:`stop`.

    :param interval: the batched sleep (``rx_interval``, :data:`RX_BATCH`).
    :param timeout: seconds one receive waits on an idle bus before the loop looks
        whether it should stop.
    """

    def __init__(self, listener: FrameQueue, interval: float, timeout: float) -> None:
        self.listener = listener
        self.interval = float(interval)
        self.timeout = timeout
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="canrls-bus-reader",
                                        daemon=True)
        self._thread.start()

    def _run(self) -> None:
        raise NotImplementedError

    def stop(self, timeout: float = 5.0) -> None:
        """Stop the thread (it finishes the frames in hand) and wait for it."""
        self._stop.set()
        self._thread.join(timeout)
        self.listener.stop()


class QueuedFrames:
    """The frames already waiting in python-can's :class:`~can.interfaces.virtual.VirtualBus`,
    taken in one go (:meth:`take`) rather than by one ``recv(0)`` each (a lock, a
    condition and a log call per frame). The one place that reads the bus's receive
    queue (``bus.queue``, a :class:`queue.Queue` of the messages ``recv`` would return,
    in order): :meth:`of` gives None, and the reader keeps ``recv``, for any other bus.
    """

    def __init__(self, q: queue.Queue[can.Message]) -> None:
        self._q = q
        #: whether the queue has a size (python-can's ``rx_queue_size``): a full one
        #: drops frames, so the reader must not sleep while it fills
        self.bounded = q.maxsize > 0

    @staticmethod
    def of(bus: can.BusABC) -> QueuedFrames | None:
        """The waiting frames of ``bus``, if it is python-can's own VirtualBus (not a
        subclass: a subclass may make frames in ``recv``) without software filters."""
        if type(bus) is not VirtualBus or bus.filters:
            return None
        q = getattr(bus, "queue", None)
        if not isinstance(q, queue.Queue) or not isinstance(getattr(q, "queue", None),
                                                            collections.deque):
            return None
        return QueuedFrames(q)

    def take(self, most: int) -> list[can.Message]:
        """Up to ``most`` frames waiting, oldest first, without waiting (as that many
        ``recv(0)``)."""
        q = self._q
        with q.mutex:
            d = q.queue
            if len(d) <= most:
                out = list(d)
                d.clear()
            else:
                out = [d.popleft() for _ in range(most)]
            if out and self.bounded:
                q.not_full.notify(len(out))
        return out


class BusReader(_Reader):
    """The thread that reads the bus into ``listener``: python-can's ``Notifier`` loop,
    taking every frame waiting at a wake-up, then sleeping ``interval`` seconds.

    An exception from ``recv`` goes to ``listener.on_error`` and the loop goes on, as
    with a ``Notifier`` whose listener handles errors.

    :param interval: seconds to sleep after a wake-up while the bus brings fewer than
        :data:`RX_BATCH` frames an interval (0: wait in ``recv`` for each frame, as a
        ``Notifier`` does).
    :param timeout: seconds one ``recv`` waits on an idle bus before the loop looks
        whether it should stop.
    :param batched: hand the frames of a wake-up to ``listener.on_block`` as one
        :class:`~canrls.can.frameblock.FrameBlock` (at most :data:`RX_BATCH_MAX`)
        instead of one by one (a machine's one reader, :class:`canrls.live.hub.BusHub`).
    """

    def __init__(self, bus: can.BusABC, listener: Any, interval: float,
                 timeout: float = 0.1, batched: bool = False) -> None:
        self.bus = bus
        self.batched = batched
        super().__init__(listener, interval, timeout)

    def _run(self) -> None:
        recv = self.bus.recv
        queued = QueuedFrames.of(self.bus)
        # an unbounded queue (python-can's virtual bus by default) never drops a frame:
        # the reader sleeps after every wake-up, so a wake-up takes rx_interval's frames
        always = queued is not None and not queued.bounded
        stop, interval = self._stop, self.interval
        batch: list[can.Message] = []
        on_block: Callable[[FrameBlock], None] = self.listener.on_block
        on_message = batch.append if self.batched else self.listener.on_message_received
        mark, taken = time.monotonic(), 0  # frames taken since mark
        while not stop.is_set():
            try:
                msg = recv(self.timeout)  # an idle bus: wait here
                if msg is None:
                    continue
                if queued is not None:  # every frame already waiting, in one go
                    on_message(msg)
                    more = queued.take(RX_BATCH_MAX - 1)
                    if self.batched:
                        batch += more
                    else:
                        for msg in more:
                            on_message(msg)
                    taken += 1 + len(more)
                while queued is None:  # every frame already waiting, without waiting
                    on_message(msg)
                    taken += 1
                    if stop.is_set() or len(batch) >= RX_BATCH_MAX:
                        break  # a source that never runs dry (a simulated drive)
                    msg = recv(0.0)
                    if msg is None:
                        break
            except Exception as exc:  # noqa: BLE001 -- as python-can's Notifier
                if batch:  # the frames taken before it, first
                    on_block(messages_to_block(batch))
                    batch.clear()
                self.listener.on_error(exc)
                continue
            if batch:
                on_block(messages_to_block(batch))
                batch.clear()
            if stop.is_set():
                return
            if interval > 0.0:
                now = time.monotonic()
                # frames per interval at the rate since mark: rate * interval < RX_BATCH
                slow = always or taken * interval < RX_BATCH * (now - mark)
                mark, taken = now, 0
                if slow:
                    # a slow bus: let frames gather in the interface (they count against
                    # the time from mark, the sleep included). A fast one fills wake-ups
                    # by itself, and the interface's buffer is not slept away
                    stop.wait(interval)


class BlockReader(_Reader):
    """The reader of a SocketCAN bus: blocks of frames off python-can's socket
    (:class:`~canrls.live.socketcan.SocketcanReceiver`, ``recvmmsg``) into ``listener``
    (:meth:`FrameQueue.on_block`), no ``can.Message`` per frame. The loop of
    :class:`BusReader`: wait up to ``timeout`` for a frame, take every frame waiting,
    sleep ``interval`` while the bus brings fewer than :data:`RX_BATCH` frames an
    interval; an exception of the socket goes to ``listener.on_error`` (after the frames
    taken with it).
    """

    def __init__(self, rx: SocketcanReceiver, listener: FrameQueue, interval: float,
                 timeout: float = 0.1) -> None:
        self.rx = rx
        super().__init__(listener, interval, timeout)

    def _run(self) -> None:
        take, messages = self.rx.take, self.rx.messages
        on_block = self.listener.on_block
        full = self.rx.capacity
        stop, interval = self._stop, self.interval
        mark, taken = time.monotonic(), 0  # frames taken since mark
        pause = 0.0  # the batched sleep, in the next receive (one wake-up, not two)
        while not stop.is_set():
            try:
                span, commands, error = take(self.timeout, pause)  # an idle bus: wait here
                pause = 0.0
                while span.n:  # every frame waiting (a full take: look again)
                    on_block(span, commands, messages)
                    taken += span.n
                    if error is not None or span.n < full or stop.is_set():
                        break
                    span, commands, error = take(0.0)
                if error is not None:
                    raise error
                if not taken:
                    continue
            except Exception as exc:  # noqa: BLE001 -- as python-can's Notifier
                pause = 0.0
                self.listener.on_error(exc)
                continue
            if interval > 0.0:
                now = time.monotonic()
                # frames per interval at the rate since mark: rate * interval < RX_BATCH
                if taken * interval < RX_BATCH * (now - mark):
                    pause = interval  # as BusReader: frames gather in the socket
                mark, taken = now, 0


class SharedBus(Protocol):
    """The one bus of a machine's axes (:class:`canrls.live.hub.BusHub`): an axis's
    :class:`BusLink` attaches to it instead of opening a bus of its own."""

    #: held while one axis sends (python-can's buses are not all thread-safe)
    tx_lock: threading.Lock

    def attach(self, link: BusLink) -> can.BusABC:
        """Route the frames of ``link.rx_ids`` to ``link.queue``; the bus (opened at the
        first axis)."""

    def detach(self, link: BusLink) -> None:
        """No more frames to ``link.queue`` (the bus closes with the last axis)."""

    def reopen(self, link: BusLink, stopping: threading.Event) -> can.BusABC | None:
        """After a failure: the bus reopened (once for all axes); None if ``stopping``."""


class BusLink:
    """The bus and its reader: open, reopen, send, and the transmit pause of faults.

    :param queue: the listener the reader feeds (kept across reopenings).
    :param factory: opens the bus (called again to reopen).
    :param config: ``send_timeout``, ``fault_hold_s``, ``reopen_min_s``/``reopen_max_s``.
    :param describe: what the bus is called in log lines when it has no ``channel_info``.
    :param rx_ids: (ID, extended) of the only frames to take (empty: every frame).
    :param batched: a reader through python-can hands ``queue`` blocks of frames
        (:meth:`BusReader` ``batched``), not frames one by one.
    """

    def __init__(self, queue: Any, factory: Callable[[], can.BusABC],
                 config: DaemonSettings, describe: str = "bus",
                 rx_ids: Sequence[tuple[int, bool]] = (), batched: bool = False) -> None:
        self.queue = queue
        self.batched = batched
        #: the machine's one bus this link takes its frames from and sends on (None: a
        #: bus of its own); set before :meth:`open`
        self.hub: SharedBus | None = None
        #: (ID, extended) of the only frames to receive (empty: every frame)
        self.rx_ids = tuple(rx_ids)
        self.factory = factory
        self.config = config
        self.describe = describe
        self.bus: can.BusABC | None = None
        self._reader: BusReader | BlockReader | None = None
        #: set in the reader's thread when ``recv`` raised
        self.failed = threading.Event()
        self._fail_exc: BaseException | None = None
        self._fault_until = 0.0
        self.bus_off = False
        self._fault_active = False
        #: frames_sent, tx_dropped, tx_paused, error_frames, bus_reopens
        self.counts: collections.Counter[str] = collections.Counter()

    def info(self) -> str:
        return str(getattr(self.bus, "channel_info", None) or self.describe)

    # ------------------------------------------------------------------ open, close
    def open(self) -> None:
        """Open the bus and start its reader (``BusError`` if it cannot be opened): a
        SocketCAN bus gets ``[daemon] rx_buffer`` and, with ``rx_bulk``, the
        :class:`BlockReader`; any other bus python-can's loop, :class:`BusReader`. On a
        machine's one bus (:attr:`hub`): attached to it, no reader of its own."""
        if self.hub is not None:
            self.bus = self.hub.attach(self)
            self.failed.clear()
            return
        bus = self.factory()
        self.bus = bus
        self.failed.clear()
        cfg = self.config
        sock = socketcan_socket(bus)
        if self.rx_ids and sock is not None:  # in the kernel: the others never come
            bus.set_filters([{"can_id": i, "can_mask": 0x1FFFFFFF if ext else 0x7FF,
                              "extended": ext} for i, ext in self.rx_ids])
        elif self.rx_ids:  # python-can's software filters would end recv(0) at the
            self.queue.accept = frozenset(self.rx_ids)  # first other frame: the queue's
        if sock is not None and cfg.rx_buffer:
            set_receive_buffer(sock, cfg.rx_buffer, self.info())
        rx = bulk_receiver(bus, command_id(cfg.own_offset)) if cfg.rx_bulk else None
        if rx is not None:
            self._reader = BlockReader(rx, self.queue, cfg.rx_s)
        else:
            self._reader = BusReader(bus, self.queue, cfg.rx_s, batched=self.batched)
        log.info("CAN bus %s read by %s", self.info(), type(self._reader).__name__)

    def close_reader(self) -> None:
        if self.hub is not None:
            self.hub.detach(self)
        r, self._reader = self._reader, None
        if r is not None:
            r.stop(timeout=5.0)

    def close(self) -> None:
        """Stop the reader and shut the bus down (a machine's one bus: the last axis
        detached shuts it down)."""
        self.close_reader()
        b, self.bus = self.bus, None
        if b is not None and self.hub is None:
            shutdown_bus(b)

    def recv_failed(self, exc: BaseException) -> None:
        """Called in the reader's thread when ``recv`` raises."""
        if not self.failed.is_set():
            self._fail_exc = exc
            self.failed.set()

    def reopen(self, stopping: threading.Event) -> None:
        """Close the failed bus and open it again, with backoff, until it opens or
        ``stopping`` is set (a machine's one bus: once for every axis)."""
        if self.hub is not None:
            bus = self.hub.reopen(self, stopping)
            if bus is not None:
                self.bus = bus
                self.failed.clear()
                self.counts["bus_reopens"] += 1
            return
        JOURNAL.warning("fault: CAN bus %s failed (%s): reopening", self.info(), self._fail_exc)
        self.close()
        delay = self.config.reopen_min_s
        while not stopping.is_set():
            try:
                self.open()
            except BusError as e:
                log.warning("%s; next attempt in %.3g s", e, delay)
                if stopping.wait(delay):
                    return
                delay = min(delay * 2.0, self.config.reopen_max_s)
                continue
            self.counts["bus_reopens"] += 1
            JOURNAL.info("fault ended: CAN bus reopened: %s", self.info())
            return

    # ------------------------------------------------------------------ transmit
    def send(self, msgs: Sequence[can.Message]) -> int:
        """Send without blocking the caller; a refused frame is dropped and counted."""
        bus = self.bus
        now = time.monotonic()
        c = self.counts
        if bus is None or now < self._fault_until or self.failed.is_set():
            c["tx_paused"] += len(msgs)  # not attempted: the bus is faulty
            return 0
        if off := self.config.own_offset:  # an axis's own IDs: moved copies
            msgs = [moved(m, off) for m in msgs]
        if self.hub is not None:
            with self.hub.tx_lock:  # the machine's other axes send on this bus too
                return self._send(bus, msgs, now)
        return self._send(bus, msgs, now)

    def _send(self, bus: can.BusABC, msgs: Sequence[can.Message], now: float) -> int:
        c = self.counts
        sent = 0
        timeout = self.config.send_timeout
        for i, m in enumerate(msgs):
            try:
                bus.send(m, timeout=timeout)
                sent += 1
            except can.CanOperationError:
                c["tx_dropped"] += 1  # transmit queue full (ENOBUFS) or similar
            except (can.CanError, OSError) as e:
                # the interface refuses to send at all: pause like an error frame
                c["tx_dropped"] += len(msgs) - i
                self._fault(now, f"send failed: {e}")
                break
        c["frames_sent"] += sent
        return sent

    # ------------------------------------------------------------------ faults
    def paused(self, now: float) -> bool:
        """Whether transmission is paused: an error frame less than ``fault_hold_s`` ago,
        or no usable bus."""
        return now < self._fault_until or self.failed.is_set() or self.bus is None

    def settle(self, now: float) -> None:
        """Once ``fault_hold_s`` passed without an error frame, the bus-off and fault
        states end (logged once). Called by the thread that sends."""
        if self.bus_off and now >= self._fault_until:
            self.bus_off = False  # no error frame for fault_hold_s: recovered
        if self._fault_active and not self.paused(now):
            self._fault_active = False
            JOURNAL.info("CAN bus fault cleared: transmission resumed")

    def _fault(self, now: float, why: str) -> None:
        if not self._fault_active:
            JOURNAL.warning("fault: CAN bus fault (%s): transmission paused", why)
        self._fault_active = True
        self._fault_until = now + self.config.fault_hold_s

    def error_frame(self, cls: int) -> None:
        """An error frame arrived (in stream order with the others); ``cls``: its
        arbitration ID, the error classes of ``linux/can/error.h``."""
        self.counts["error_frames"] += 1
        now = time.monotonic()
        if cls & _CAN_ERR_RESTARTED and not cls & _CAN_ERR_BUSOFF:
            if self.bus_off:
                log.info("CAN controller restarted after bus-off")
            self.bus_off = False
            self._fault_until = now  # resume at once
            return
        if cls & _CAN_ERR_BUSOFF:
            self.bus_off = True
        self._fault(now, f"error frame 0x{cls:X}{' (bus-off)' if self.bus_off else ''}")
