"""Every axis of a machine in one process: one :class:`~canrls.live.daemon.Daemon` per
axis, each with its own bus reader, estimator, checkpoint, counters and own frames, started,
stopped and reported together (:class:`MachineDaemon`)."""

from __future__ import annotations

import threading
from collections.abc import Callable, Mapping

from canrls.live.daemon import Daemon, serve, wait_until

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
        return wait_until(lambda: predicate(self), timeout)

    def run(self, duration: float | None = None) -> int:
        """Start, serve until SIGTERM/SIGINT (or ``duration`` s) or an axis fails, stop;
        SIGHUP reloads every axis's model. The exit status as :meth:`Daemon.run`'s."""
        return serve(self, self._stopping, duration)
