"""Every axis of a machine in one process: one :class:`~canrls.live.daemon.Daemon` per
axis, each with its own bus reader, estimator, checkpoint, counters and own frames, started,
stopped and reported together (:class:`MachineDaemon`)."""

from __future__ import annotations

import signal
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

from canrls.live.daemon import Daemon

__all__ = ["MachineDaemon"]


class MachineDaemon:
    """The daemons of a machine's axes, by axis name. Nothing is shared between them but
    the process: a fault on one axis (garbage, silence, a flood, a bad command) reaches
    its own reader, estimator and frames only."""

    def __init__(self, daemons: Mapping[str, Daemon]) -> None:
        self.daemons = dict(daemons)
        self._stopping = threading.Event()

    @property
    def failure(self) -> BaseException | None:
        """The first axis's internal error, if any ended its threads."""
        return next((d.failure for d in self.daemons.values() if d.failure is not None), None)

    def start(self) -> None:
        """Start every axis (those started are stopped again when one cannot start)."""
        started = []
        try:
            for d in self.daemons.values():
                d.start()
                started.append(d)
        except BaseException:
            for d in started:
                d.stop()
            raise

    def stop(self) -> None:
        for d in self.daemons.values():
            d.stop()

    def request_stop(self) -> None:
        self._stopping.set()

    def request_reload(self) -> None:
        for d in self.daemons.values():
            d.request_reload()

    def wait_for(self, predicate: Callable[[MachineDaemon], bool], timeout: float) -> bool:
        """Poll ``predicate(self)`` until true or ``timeout`` seconds (tests)."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if predicate(self):
                return True
            time.sleep(0.005)
        return predicate(self)

    def run(self, duration: float | None = None) -> int:
        """Start, serve until SIGTERM/SIGINT (or ``duration`` s) or an axis fails, stop;
        SIGHUP reloads every axis's model. The exit status as :meth:`Daemon.run`'s."""
        handlers: dict[int, Any] = {}
        if threading.current_thread() is threading.main_thread():
            for sig, fn in ((signal.SIGTERM, lambda *_: self.request_stop()),
                            (signal.SIGINT, lambda *_: self.request_stop()),
                            (signal.SIGHUP, lambda *_: self.request_reload())):
                handlers[sig] = signal.signal(sig, fn)
        try:
            self.start()
            end = None if duration is None else time.monotonic() + duration
            while not self._stopping.is_set() and self.failure is None:
                left = 0.2 if end is None else min(0.2, end - time.monotonic())
                if left <= 0:
                    break
                self._stopping.wait(left)
        finally:
            self.stop()
            for sig, old in handlers.items():
                signal.signal(sig, old)
        return 0 if self.failure is None else 1
