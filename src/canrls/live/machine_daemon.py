"""Every axis of a machine in one process: one :class:`~canrls.live.daemon.Daemon` per
axis, each with its own estimator, checkpoint, counters and own frames, on the machine's
one bus (:class:`~canrls.live.hub.BusHub`), started, stopped and reported together
(:class:`MachineDaemon`)."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Mapping, Sequence

from canrls.core.errors import CanrlsError
from canrls.live.bus_link import open_bus
from canrls.live.daemon import Daemon, serve, wait_until
from canrls.live.hub import BusHub
from canrls.processor.axes import check_own

__all__ = ["MachineDaemon"]

log = logging.getLogger(__name__)


class MachineDaemon:
    """The daemons of a machine's axes, by axis name. They share the process and the
    bus: the axes on the same bus arguments take their frames from one
    :class:`~canrls.live.hub.BusHub` (one connection, one reader, each frame routed by
    its ID to its axis's queue) and send on it; nothing else. A fault on one axis
    (garbage, silence, a flood, a bad command) reaches its own queue, estimator and
    frames only. An axis that records the bus, or whose bus a factory opens, keeps a
    bus of its own.

    :param build: ``build(name)``: a new axis's daemon (not started), for a reload.
    :param axes: the axes the configuration declares now (its file read again on SIGHUP:
        the machine is checked as at a start, :meth:`AppConfig.axis_configs`).
    """

    def __init__(self, daemons: Mapping[str, Daemon],
                 build: Callable[[str], Daemon] | None = None,
                 axes: Callable[[], Sequence[str]] | None = None) -> None:
        self.daemons = dict(daemons)
        #: the machine's buses, by their arguments
        self._hubs: dict[str, BusHub] = {}
        for d in self.daemons.values():
            self._join(d)
        self._build = build
        self._axes = axes
        self._stopping = threading.Event()
        self._reload = threading.Event()
        self._running = False

    def _join(self, d: Daemon) -> None:
        """Put ``d`` on the machine's bus of its arguments (if it may share one)."""
        args = d.shared_bus()
        if args is None:
            return
        key = repr(sorted(args.items()))
        hub = self._hubs.get(key)
        if hub is None:
            hub = self._hubs[key] = BusHub(lambda: open_bus(args), d.config,
                                           describe=str(args))
        d.join(hub)

    @property
    def reader_cpu_s(self) -> float:
        """Thread CPU time of the machine's bus readers [s] (the axes' own
        ``listener_cpu_s`` counts only a bus of their own)."""
        return sum(h.cpu for h in self._hubs.values())

    @property
    def foreign_frames(self) -> int:
        """Frames on the machine's buses that no axis takes (error frames aside)."""
        return sum(h.foreign for h in self._hubs.values())

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
        self._running = True

    def stop(self) -> None:
        self._running = False
        for d in self.daemons.values():
            d.stop()

    def request_stop(self) -> None:
        self._stopping.set()

    def request_reload(self) -> None:
        """SIGHUP: every axis reloads its model; axes added to or removed from the
        configuration start or stop at the next wake-up (:meth:`reconcile`)."""
        for d in self.daemons.values():
            d.request_reload()
        self._reload.set()

    def reconcile(self) -> None:
        """After a reload request: start the axes the configuration added, stop those it
        removed; the others run on untouched. A configuration a start would refuse, or
        a new axis whose frames would meet a running one's, changes nothing (logged)."""
        if not self._reload.is_set() or self._axes is None or self._build is None:
            return
        self._reload.clear()
        try:
            want = list(self._axes())
            added = {n: self._build(n) for n in want if n not in self.daemons}
            kept = {n: d for n, d in {**self.daemons, **added}.items() if n in want}
            check_own({f"axis {n}": d.protocol for n, d in kept.items()},
                      {f"axis {n}": d.config.own_offset for n, d in kept.items()})
        except CanrlsError as e:
            log.warning("reload: the axes stay as they are: %s", e)
            return
        for n in [n for n in self.daemons if n not in want]:
            self.daemons.pop(n).stop()
            log.info("reload: axis %s removed", n)
        for n, d in added.items():
            self._join(d)
            if self._running:
                d.start()
            self.daemons[n] = d
            log.info("reload: axis %s added", n)

    def wait_for(self, predicate: Callable[[MachineDaemon], bool], timeout: float) -> bool:
        """Poll ``predicate(self)`` until true or ``timeout`` seconds (tests)."""
        return wait_until(lambda: predicate(self), timeout)

    def run(self, duration: float | None = None) -> int:
        """Start, serve until SIGTERM/SIGINT (or ``duration`` s) or an axis fails, stop;
        SIGHUP reloads every axis's model and adds or removes axes. The exit status as
        :meth:`Daemon.run`'s."""
        return serve(self, self._stopping, duration, each=self.reconcile)
