"""One bus for every axis of a machine: one connection, one reader, frames routed by ID.

::

    bus --reader--> BusHub.on_block: a block of frames, each frame's axis found
                    by its (ID, extended) in one sorted table (np.searchsorted),
                    the block cut per axis in one stable sort --> each axis's FrameQueue

Each axis's :class:`~canrls.live.bus_link.BusLink` attaches to the hub instead of opening a
bus of its own (:class:`~canrls.live.bus_link.SharedBus`); it sends on the hub's bus. Why one
reader rather than one per axis, and the figures: docs/daemon.md, *A machine's axes*.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import can
import numpy as np
import numpy.typing as npt

from canrls.can.frameblock import FrameBlock
from canrls.live.bus_link import BusLink, FrameQueue, messages_to_block
from canrls.live.daemon_settings import DaemonSettings
from canrls.live.socketcan import Span, to_block

__all__ = ["BusHub"]

log = logging.getLogger(__name__)


def _keys(ids: npt.NDArray[np.uint32], extended: npt.NDArray[np.bool_]) -> np.ndarray:
    """One integer per (ID, extended): the ID, plus 2^32 for an extended one."""
    return ids.astype(np.int64) | (extended.astype(np.int64) << 32)


@dataclass(frozen=True)
class _Routes:
    """Which axis takes which frame: ``keys`` sorted, ``owner[i]`` the index in
    ``queues`` of the one axis taking ``keys[i]`` (-2: several, see ``shared``);
    ``everything``: the queues of axes that take every frame."""

    keys: np.ndarray
    owner: np.ndarray
    queues: tuple[FrameQueue, ...]
    shared: tuple[np.ndarray, ...]
    everything: tuple[FrameQueue, ...]

    @staticmethod
    def of(links: Sequence[BusLink]) -> _Routes:
        queues: list[FrameQueue] = []
        everything: list[FrameQueue] = []
        takers: dict[int, list[int]] = {}
        for link in links:
            if not link.rx_ids:
                everything.append(link.queue)
                continue
            k = len(queues)
            queues.append(link.queue)
            for i, ext in link.rx_ids:
                takers.setdefault(int(i) | (int(bool(ext)) << 32), []).append(k)
        keys = np.array(sorted(takers), np.int64)
        owner = np.array([t[0] if len(t) == 1 else -2 for t in
                          (takers[int(k)] for k in keys)], np.int64)
        # per axis: the keys it shares with another axis
        shared = tuple(np.array(sorted(key for key, t in takers.items()
                                       if len(t) > 1 and k in t), np.int64)
                       for k in range(len(queues)))
        return _Routes(keys, owner, tuple(queues), shared, tuple(everything))


class BusHub:
    """The one bus of a machine's axes (a :class:`~canrls.live.bus_link.SharedBus`): opened
    when the first axis attaches, closed when the last detaches, reopened once for all
    when it fails. Its reader hands it blocks of frames (:meth:`on_block`); each frame
    goes to the queue of the axis whose (ID, extended) it carries, in stream order;
    an error frame goes to every axis; a frame of no axis is counted
    (:attr:`foreign`), never queued.

    :param factory: opens the bus (called again to reopen).
    :param config: the reader's settings (``rx_interval``, ``rx_bulk``, ``rx_buffer``,
        the reopening delays); the axes' own settings stay theirs.
    :param describe: what the bus is called in log lines.
    """

    def __init__(self, factory: Callable[[], can.BusABC], config: DaemonSettings,
                 describe: str = "bus") -> None:
        self._link = BusLink(self, factory, config, describe, batched=True)
        self._links: list[BusLink] = []
        self._routes = _Routes.of(())
        self._lock = threading.Lock()  # the axes attached
        #: one axis reopens, the others wait (not holding _lock: axes may stop meanwhile)
        self._reopening = threading.Lock()
        self.tx_lock = threading.Lock()
        #: frames of no attached axis (error frames aside)
        self.foreign = 0
        #: frames routed to the axes (each frame once)
        self.frames = 0
        #: thread CPU time of the reader's thread since its first block [s]
        self.cpu = 0.0
        self._cpu0: float | None = None

    # ------------------------------------------------------------------ SharedBus
    def attach(self, link: BusLink) -> can.BusABC:
        with self._lock:
            link.queue.clock_cpu = False  # the hub's reader is clocked here, once
            self._links.append(link)
            self._routes = _Routes.of(self._links)
            if self._link.bus is None:
                try:
                    self._link.open()
                except BaseException:
                    self._links.remove(link)
                    self._routes = _Routes.of(self._links)
                    raise
            assert self._link.bus is not None
            return self._link.bus

    def detach(self, link: BusLink) -> None:
        with self._lock:
            if link not in self._links:
                return
            self._links.remove(link)
            self._routes = _Routes.of(self._links)
            if not self._links:
                self._link.close()
                if self.foreign:
                    log.info("%s: %d frames of no axis were not taken", self.info(),
                             self.foreign)

    def reopen(self, link: BusLink, stopping: threading.Event) -> can.BusABC | None:
        with self._reopening:
            if self._link.failed.is_set() or self._link.bus is None:
                self._link.reopen(stopping)
            bus = self._link.bus
            if self._link.failed.is_set() or bus is None:
                return None  # stopping before the bus came back
            with self._lock:
                for other in self._links:  # every axis sends on the new bus
                    other.bus = bus
            return bus

    def info(self) -> str:
        return self._link.info()

    # ------------------------------------------------------------------ the reader's side
    def on_block(self, block: FrameBlock | Span, commands: int | None = None,
                 messages: object = None) -> None:
        """A block of frames off the bus (the reader's thread): each axis's frames, in
        their order, to its queue (its ``on_block``: its limit, its commands)."""
        if isinstance(block, Span):
            block = to_block([block])
        r = self._routes
        n = len(block)
        self.frames += n
        for q in r.everything:
            q.on_block(block)
        if r.queues:
            self._route(block, r)
        elif not r.everything:
            self.foreign += int(n - np.count_nonzero(block.is_error))
        now = time.thread_time()
        if self._cpu0 is None:
            self._cpu0 = now
        self.cpu = now - self._cpu0

    def _route(self, block: FrameBlock, r: _Routes) -> None:
        key = _keys(block.arbitration_id, block.is_extended)
        pos = np.minimum(np.searchsorted(r.keys, key), len(r.keys) - 1)
        err = block.is_error
        # the axis of each frame: k >= 0; -1 none; -2 several; -3 an error frame (all)
        owner = np.where(err, -3, np.where(r.keys[pos] == key, r.owner[pos], -1))
        if not r.everything:
            self.foreign += int(np.count_nonzero(owner == -1))
        first = int(owner[0])
        if first >= 0 and (owner == first).all():  # a block of one axis's frames
            r.queues[first].on_block(block)
            return
        if not (owner < -1).any():  # one vectorised step: the rows of axis k, in order
            order = np.argsort(owner, kind="stable")  # a frame of no axis sorts first
            bounds = np.searchsorted(owner[order], np.arange(len(r.queues) + 1))
            for k, q in enumerate(r.queues):
                lo, hi = bounds[k], bounds[k + 1]
                if hi > lo:
                    q.on_block(block if hi - lo == len(block)
                               else block.take(order[lo:hi]))
            return
        # error frames (every axis), IDs of several axes: a mask per axis
        several = owner == -2
        for k, q in enumerate(r.queues):
            rows = (owner == k) | err
            if r.shared[k].size and several.any():
                rows |= several & np.isin(key, r.shared[k])
            if rows.any():
                q.on_block(block.take(rows))

    def on_message_received(self, msg: can.Message) -> None:
        """One frame (a reader that is not batched): a block of one."""
        self.on_block(messages_to_block([msg]))

    def on_error(self, exc: Exception) -> None:
        """The bus's ``recv`` raised: the hub's link and every axis fail (their
        supervisors call :meth:`reopen`)."""
        self._link.recv_failed(exc)
        for link in list(self._links):
            link.queue.report(exc)
        time.sleep(0.05)  # the reader retries recv at once: do not spin

    def stop(self) -> None:
        """The reader stops (reopened, or the last axis detached)."""
