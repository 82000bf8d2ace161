"""The bulk receive path of a SocketCAN bus: python-can's socket, read in blocks.

python-can's :class:`~can.interfaces.socketcan.SocketcanBus` opens, binds, filters and
sends on its raw CAN socket as always; only the receive is done here, on that same
socket (``bus.socket``): :class:`SocketcanReceiver` waits on it with the interpreter
lock released and takes every frame waiting in one ``recvmmsg`` (the C extension
``canrls._rx``), straight into the arrays of a :class:`~canrls.can.frameblock.FrameBlock`.
The block is, field for field, what python-can's ``recv`` and
:func:`canrls.live.bus.messages_to_block` make of the same datagrams (the timestamp of
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

__all__ = ["AVAILABLE", "RX_CAPACITY", "Received", "SocketcanReceiver", "bulk_receiver",
           "set_receive_buffer", "socketcan_socket"]

log = logging.getLogger(__name__)

#: whether this platform has the bulk receive (recvmmsg: Linux)
AVAILABLE = bool(_rx.AVAILABLE)
#: most frames one :meth:`SocketcanReceiver.recv` takes (the reader calls again at once
#: when it took that many)
RX_CAPACITY = 1024
# SO_RCVBUFFORCE (asm-generic/socket.h; the socket module names it only on some builds)
_SO_RCVBUFFORCE = getattr(socket, "SO_RCVBUFFORCE", 33)


@dataclass(frozen=True)
class Received:
    """What one :meth:`SocketcanReceiver.recv` took.

    :ivar block: the frames (empty: none arrived within the timeout).
    :ivar aux: uint8 (N, 2): python-can's message fields that a block does not keep, for
        :meth:`SocketcanReceiver.messages` (column 0: bit 0 CAN FD, bit 1 bit rate
        switch, bit 2 error state indicator, bit 3 sent by this host; column 1: the
        ``dlc`` python-can's message carries).
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
    :param capacity: most frames one :meth:`recv` takes.
    """

    def __init__(self, sock: socket.socket, channel: str | None = None,
                 capacity: int = RX_CAPACITY) -> None:
        self.sock = sock
        self.channel = channel or None
        self.capacity = capacity
        self._t = np.zeros(capacity, np.float64)
        self._id = np.zeros(capacity, np.uint32)
        self._ext = np.zeros(capacity, np.bool_)
        self._rtr = np.zeros(capacity, np.bool_)
        self._err = np.zeros(capacity, np.bool_)
        self._dlc = np.zeros(capacity, np.uint8)
        self._data = np.zeros((capacity, _rx.DATA_WIDTH), np.uint8)
        self._aux = np.zeros((capacity, 2), np.uint8)

    def recv(self, timeout: float) -> Received:
        """Wait up to ``timeout`` seconds for a frame (0: not at all), then take every
        frame waiting (at most :attr:`capacity`).

        :raises OSError: the socket failed (closed, interface down) before a frame was
            taken; after frames, it comes back in :attr:`Received.error`.
        """
        fd = self.sock.fileno()  # -1 once python-can closed it: EBADF
        n, error = _rx.recv(fd, timeout, self._t, self._id, self._ext, self._rtr, self._err,
                            self._dlc, self._data, self._aux)
        if n == 0:
            return Received(FrameBlock.empty(), self._aux[:0].copy(), error)
        dlc = self._dlc[:n].copy()
        # messages_to_block's width: max(8, the longest data)
        width = max(8, int(dlc.max()))
        block = FrameBlock(t=self._t[:n].copy(), arbitration_id=self._id[:n].copy(),
                           is_extended=self._ext[:n].copy(), is_remote=self._rtr[:n].copy(),
                           is_error=self._err[:n].copy(), dlc=dlc,
                           data=self._data[:n, :width].copy())
        return Received(block, self._aux[:n].copy(), error)

    def messages(self, got: Received, n: int | None = None) -> list[can.Message]:
        """The ``can.Message`` objects python-can's ``recv`` would have made of the
        frames (the first ``n``; the recorder, ``[daemon] record``)."""
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


def bulk_receiver(bus: can.BusABC) -> SocketcanReceiver | None:
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
    return SocketcanReceiver(sock, getattr(bus, "channel", None))


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
