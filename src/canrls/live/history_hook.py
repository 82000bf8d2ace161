"""The daemon's published parameters, handed to a history at a slow rate (``[history]``).

:class:`HistoryHook` is offered the estimates after every publication (in the estimator
thread: a clock check, nothing more, unless a snapshot is due) and passes one snapshot
every ``interval`` seconds, and the last one at stop, to a writer thread that calls
``append`` (``canrls run`` hands in the fleet history's
:class:`~canrls.fleet.live_appender.LiveAppender`). A slow or failing database never holds the
estimator: snapshots wait in a short queue, the oldest dropped (counted) when it is
full, and a failed append is logged and counted.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from canrls.estimation.estimates import Estimates

__all__ = ["HistoryHook", "Snapshot"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Snapshot:
    """The estimates as published at wall-clock time ``t`` (epoch s), ``seq``-th of the
    run."""

    seq: int
    t: float
    estimates: Estimates


class HistoryHook:
    """Snapshots of the published estimates every ``interval`` s to ``append``."""

    def __init__(self, append: Callable[[Snapshot], None], interval: float, *,
                 close: Callable[[], None] | None = None, queue_size: int = 16) -> None:
        self.append = append
        self.interval = float(interval)
        self._close = close
        self._queue: collections.deque[Snapshot] = collections.deque(maxlen=queue_size)
        self._wake = threading.Condition()
        self._stop = False
        self._next: float | None = None
        self._seq = 0
        #: snapshots appended, dropped (queue full), failed (append raised)
        self.appended = self.dropped = self.failed = 0
        self._thread = threading.Thread(target=self._writer, name="canrls history",
                                        daemon=True)
        self._thread.start()

    def offer(self, now: float, estimates: Callable[[], Estimates], *,
              final: bool = False) -> None:
        """After a publication at ``now`` (monotonic): a snapshot if one is due (the
        first at once), or ``final``."""
        if self._next is not None and now < self._next and not final:
            return
        self._next = now + self.interval
        snap = Snapshot(self._seq, time.time(), estimates())
        self._seq += 1
        with self._wake:
            if len(self._queue) == self._queue.maxlen:
                self.dropped += 1
            self._queue.append(snap)
            self._wake.notify()

    def _writer(self) -> None:
        while True:
            with self._wake:
                while not self._queue and not self._stop:
                    self._wake.wait()
                if not self._queue:
                    return
                snap = self._queue.popleft()
            try:
                self.append(snap)
                self.appended += 1
            except Exception as e:  # the daemon goes on; the history misses one snapshot
                self.failed += 1
                if self.failed <= 3 or self.failed % 100 == 0:
                    log.error("history: snapshot %d not stored (%d failed so far): %s",
                              snap.seq, self.failed, e)

    def close(self, timeout: float = 10.0) -> None:
        """Store what is queued (waiting up to ``timeout`` s), then stop. Idempotent."""
        with self._wake:
            self._stop = True
            self._wake.notify()
        self._thread.join(timeout)
        if self._thread.is_alive():
            log.error("history: %d snapshots not stored at stop (the database is slow)",
                      len(self._queue))
        if self._close is not None:
            close, self._close = self._close, None
            close()
