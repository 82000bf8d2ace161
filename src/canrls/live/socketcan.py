"""The bulk receive path of a SocketCAN bus: python-can's socket, read in blocks.

python-can's :class:`~can.interfaces.socketcan.SocketcanBus` opens, binds, filters and
sends on its raw CAN socket as always; only the receive is done here, on that same
socket (``bus.socket``): :class:`SocketcanReceiver` waits on it with the interpreter
lock released and takes every frame waiting in one ``recvmmsg`` (the C extension
``canrls._rx``), straight into the arrays of a :class:`~canrls.can.frameblock.FrameBlock`.
The block is, field for field, what python-can's ``recv`` and
:func:`canrls.live.bus_link.messages_to_block` make of the same datagrams (the timestamp of
``SO_TIMESTAMPNS``, the id and its EFF/RTR/ERR flags, the data length and bytes of a
classic 16-byte ``struct can_frame`` and a 72-byte ``canfd_frame``), without a
``can.Message`` per frame: ``docs/daemon.md``, *The reader*.

:func:`set_receive_buffer` asks the kernel for a larger receive buffer on that socket
(``[daemon] rx_buffer``).
"""

from __future__ import annotations

import errno
import logging
import socket
from dataclasses import dataclass

import can
import numpy as np
import numpy.typing as npt

from canrls import _rx
from canrls.can.frameblock import FrameBlock

__all__ = ["ARENA", "AVAILABLE", "Arena", "RX_CAPACITY", "Received", "SocketcanReceiver",
           "Span", "bulk_receiver", "set_receive_buffer", "socketcan_socket", "to_block"]

log = logging.getLogger(__name__)

#: whether this platform has the bulk receive (recvmmsg: Linux)
AVAILABLE = bool(_rx.AVAILABLE)
#: most frames one :meth:`SocketcanReceiver.take` takes (the reader calls again at once
#: when it took that many)
RX_CAPACITY = 1024
#: frames of one arena: the receiver writes the frames of successive calls one after the
#: other into it (a new one when the rest is shorter than :data:`RX_CAPACITY`)
ARENA = 16384
# SO_RCVBUFFORCE (asm-generic/socket.h; the socket module names it only on some builds)
_SO_RCVBUFFORCE = getattr(socket, "SO_RCVBUFFORCE", 33)


class Arena:
    """The arrays the C receive writes frames into, :data:`ARENA` rows (or ``rows``)."""

    __slots__ = ("t", "arbitration_id", "is_extended", "is_remote", "is_error", "dlc",
                 "data", "aux", "arrays")

    def __init__(self, rows: int = ARENA) -> None:
        self.t = np.zeros(rows, np.float64)
        self.arbitration_id = np.zeros(rows, np.uint32)
        self.is_extended = np.zeros(rows, np.bool_)
        self.is_remote = np.zeros(rows, np.bool_)
        self.is_error = np.zeros(rows, np.bool_)
        self.dlc = np.zeros(rows, np.uint8)
        self.data = np.zeros((rows, _rx.DATA_WIDTH), np.uint8)
        #: python-can's message fields a block does not keep: column 0 bit 0 CAN FD,
        #: bit 1 bit rate switch, bit 2 error state indicator, bit 3 sent by this host;
        #: column 1 the ``dlc`` python-can's message carries
        self.aux = np.zeros((rows, 2), np.uint8)
        self.arrays = (self.t, self.arbitration_id, self.is_extended, self.is_remote,
                       self.is_error, self.dlc, self.data, self.aux)


class Span:
    """Frames ``start .. start + n - 1`` of an :class:`Arena`: what one receive took,
    queued as it is (no copy, no block built in the reader's thread); :func:`to_block`
    makes the block."""

    __slots__ = ("arena", "start", "n")

    def __init__(self, arena: Arena, start: int, n: int) -> None:
        self.arena, self.start, self.n = arena, start, n

    def __len__(self) -> int:
        return self.n

    def head(self, k: int) -> Span:
        """The first ``k`` frames."""
        return Span(self.arena, self.start, k)

    def tail(self, k: int) -> Span:
        """The frames after the first ``k``."""
        return Span(self.arena, self.start + k, self.n - k)


def to_block(spans: list[Span]) -> FrameBlock:
    """One block of the frames of ``spans`` (in order; spans that follow each other in
    an arena are copied in one piece): field for field what python-can's ``recv`` and
    :func:`canrls.live.bus_link.messages_to_block` give, the data as wide as the longest (at
    least 8)."""
    runs: list[Span] = []
    for s in spans:
        last = runs[-1] if runs else None
        if last is not None and last.arena is s.arena and last.start + last.n == s.start:
            runs[-1] = Span(s.arena, last.start, last.n + s.n)
        elif s.n:
            runs.append(s)
    if not runs:
        return FrameBlock.empty()

    def field(name: str) -> np.ndarray:
        parts = [getattr(r.arena, name)[r.start:r.start + r.n] for r in runs]
        return parts[0].copy() if len(parts) == 1 else np.concatenate(parts)

    dlc = field("dlc")
    width = max(8, int(dlc.max()))  # messages_to_block's width
    data = [r.arena.data[r.start:r.start + r.n, :width] for r in runs]
    return FrameBlock(t=field("t"), arbitration_id=field("arbitration_id"),
                      is_extended=field("is_extended"), is_remote=field("is_remote"),
                      is_error=field("is_error"), dlc=dlc,
                      data=np.ascontiguousarray(data[0]) if len(data) == 1
                      else np.concatenate(data))


@dataclass(frozen=True)
class Received:
    """What one :meth:`SocketcanReceiver.recv` took.

    :ivar block: the frames (empty: none arrived within the timeout).
    :ivar aux: uint8 (N, 2): python-can's message fields a block does not keep
        (:attr:`Arena.aux`).
    :ivar error: raise it once the frames are delivered (an ``OSError`` of the socket
        after frames were taken, or a ``ValueError``: a datagram python-can would have
        refused); None: none.
    """

    block: FrameBlock
    aux: npt.NDArray[np.uint8]
    error: BaseException | None = None


class SocketcanReceiver:
    """Reads frames off the socket of a python-can ``SocketcanBus`` in blocks.

    :param sock: the bus's socket (``bus.socket``); python-can keeps it, sends on it and
        closes it.
    :param channel: the channel the messages of :meth:`messages` name.
    :param capacity: most frames one :meth:`take` takes.
    :param command_id: the standard id :meth:`take` counts frames of (the daemon's
        command frames, which hurry the estimator).
    """

    def __init__(self, sock: socket.socket, channel: str | None = None,
                 capacity: int = RX_CAPACITY, command_id: int = -1) -> None:
        self.sock = sock
        self.channel = channel or None
        self.capacity = capacity
        self.command_id = command_id
        self._arena = Arena(max(ARENA, capacity))
        self._pos = 0

    def take(self, timeout: float, pause: float = 0.0
             ) -> tuple[Span, int, BaseException | None]:
        """Sleep ``pause`` seconds, wait up to ``timeout`` seconds for a frame (0: not at
        all), then take every frame waiting (at most :attr:`capacity`), the interpreter
        lock released throughout. Returns the frames (a :class:`Span`), how many of them
        are command frames, and an error to raise once they are delivered (an
        ``OSError`` of the socket after frames, a ``ValueError`` for a datagram
        python-can would refuse), or None.

        :raises OSError: the socket failed (closed, interface down) before a frame.
        """
        arena, pos = self._arena, self._pos
        if len(arena.t) - pos < self.capacity:
            arena, pos = self._arena, self._pos = Arena(len(arena.t)), 0
        n, commands, error = _rx.recv(self.sock.fileno(), pause, timeout, pos, self.capacity,
                                      self.command_id, *arena.arrays)
        self._pos = pos + n
        return Span(arena, pos, n), commands, error

    def recv(self, timeout: float) -> Received:
        """:meth:`take` as one block, with its messages' other fields.

        :raises OSError: as :meth:`take`.
        """
        span, _, error = self.take(timeout)
        a = span.arena.aux[span.start:span.start + span.n].copy()
        return Received(to_block([span]), a, error)

    def messages(self, got: Received | Span, n: int | None = None) -> list[can.Message]:
        """The ``can.Message`` objects python-can's ``recv`` would have made of the
        frames (the first ``n``; the recorder, ``[daemon] record``)."""
        if isinstance(got, Span):
            b, aux = to_block([got]), got.arena.aux[got.start:got.start + got.n]
        else:
            b, aux = got.block, got.aux
        n = len(b) if n is None else n
        return [can.Message(
            timestamp=float(b.t[k]), channel=self.channel,
            arbitration_id=int(b.arbitration_id[k]), is_extended_id=bool(b.is_extended[k]),
            is_remote_frame=bool(b.is_remote[k]), is_error_frame=bool(b.is_error[k]),
            is_fd=bool(aux[k, 0] & _rx.AUX_FD), is_rx=not aux[k, 0] & _rx.AUX_TX,
            bitrate_switch=bool(aux[k, 0] & _rx.AUX_BRS),
            error_state_indicator=bool(aux[k, 0] & _rx.AUX_ESI),
            dlc=int(aux[k, 1]), data=b.data[k, :b.dlc[k]].tobytes())
            for k in range(n)]


def socketcan_socket(bus: can.BusABC) -> socket.socket | None:
    """The raw CAN socket of ``bus`` if it is python-can's ``SocketcanBus`` (isinstance),
    else None."""
    try:
        from can.interfaces.socketcan import SocketcanBus
    except ImportError:  # pragma: no cover - python-can always has it
        return None
    return bus.socket if isinstance(bus, SocketcanBus) else None


def bulk_receiver(bus: can.BusABC, command_id: int = -1) -> SocketcanReceiver | None:
    """A :class:`SocketcanReceiver` on ``bus`` if it is python-can's ``SocketcanBus`` and
    the bulk receive applies; None: read it through python-can (any other interface; no
    ``recvmmsg`` on this platform; filters python-can applies in software, as on a
    socket whose kernel filter it could not set)."""
    sock = socketcan_socket(bus)
    if sock is None:
        return None
    if not AVAILABLE:
        log.info("SocketCAN bulk receive unavailable on this platform (no recvmmsg): "
                 "frames are read through python-can")
        return None
    # BusABC.recv filters in software unless the interface says its kernel did (python-can
    # sets _is_filtered once CAN_RAW_FILTER took the filters)
    if bus.filters and not getattr(bus, "_is_filtered", False):
        log.info("python-can filters %s in software: frames are read through python-can",
                 bus.filters)
        return None
    return SocketcanReceiver(sock, getattr(bus, "channel", None), command_id=command_id)


def set_receive_buffer(sock: socket.socket, size: int, describe: str = "socket") -> int | None:
    """Ask for a receive buffer of ``size`` bytes on ``sock``; returns what the kernel
    granted (``SO_RCVBUF`` read back, which the kernel reports doubled: its bookkeeping),
    None if it refused (logged as a warning: the socket keeps its buffer).

    ``SO_RCVBUFFORCE`` first (a process with ``CAP_NET_ADMIN`` may exceed the limit),
    else ``SO_RCVBUF``, which the kernel caps at ``net.core.rmem_max`` without saying so:
    the granted size is logged, with the sysctl to raise when it is short.
    """
    try:
        try:
            sock.setsockopt(socket.SOL_SOCKET, _SO_RCVBUFFORCE, size)
        except PermissionError:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, size)
        granted = int(sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF))
    except OSError as e:
        log.warning("%s: receive buffer of %d bytes refused (%s); it keeps its own. Raise "
                    "net.core.rmem_max (sysctl -w net.core.rmem_max=%d) or give the service "
                    "CAP_NET_ADMIN", describe, size,
                    e.strerror or errno.errorcode.get(e.errno or 0, e), size)
        return None
    if granted < size:
        log.warning("%s: receive buffer %d bytes asked, the kernel granted %d (it caps at "
                    "net.core.rmem_max: sysctl -w net.core.rmem_max=%d, or CAP_NET_ADMIN)",
                    describe, size, granted, size)
    else:
        log.info("%s: receive buffer %d bytes (asked %d)", describe, granted, size)
    return granted
