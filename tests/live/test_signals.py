"""Stop signals in any timing: the daemon's handlers never act inside the code a signal
interrupts (:class:`~canrls.live.signals.SignalRelay`)."""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from canrls.live.daemon import serve

_HANDLED = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)


class _Target:
    """A daemon's contract for :func:`serve`; its ``start`` raises ``signals`` while it
    holds the lock its ``request_stop`` takes, as ``Event.wait`` holds its event's lock
    when a signal interrupts it (the handler that set the event waited on that lock for
    ever, each further signal nesting another handler in the wait: RecursionError)."""

    failure = None

    def __init__(self, signals: list[int]) -> None:
        self.signals = signals
        self.lock = threading.Lock()
        self.stopping = threading.Event()
        self.requests: list[str] = []
        self.stops = 0

    def start(self) -> None:
        with self.lock:
            for sig in self.signals:
                signal.raise_signal(sig)

    def request_stop(self) -> None:
        with self.lock:
            self.requests.append("stop")
        self.stopping.set()

    def request_reload(self) -> None:
        with self.lock:
            self.requests.append("reload")

    def stop(self) -> None:
        self.stops += 1


class _Deadlock(Exception):
    pass


@contextmanager
def _deadlock_alarm(seconds: float) -> Iterator[None]:
    """SIGALRM after ``seconds`` raises :class:`_Deadlock` where the main thread waits."""
    def ring(signum: int, frame: Any) -> None:
        raise _Deadlock(f"the main thread still waited after {seconds} s")

    old = signal.signal(signal.SIGALRM, ring)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


def test_signals_inside_the_lock_their_action_takes_are_one_clean_stop() -> None:
    """40 SIGTERM, SIGINT and SIGHUP raised while the main thread holds the lock that the
    target's request_stop takes: every one is acted on, in order, once the lock is free;
    serve stops the target once and returns 0; the handlers are restored."""
    before = {s: signal.getsignal(s) for s in _HANDLED}
    signals = [(signal.SIGTERM, signal.SIGINT, signal.SIGHUP, signal.SIGTERM)[k % 4]
               for k in range(40)]
    target = _Target(signals)
    with _deadlock_alarm(5.0):
        status = serve(target, target.stopping, duration=30.0)
    assert status == 0 and target.stops == 1
    assert target.requests == ["reload" if s == signal.SIGHUP else "stop" for s in signals]
    assert {s: signal.getsignal(s) for s in _HANDLED} == before


def test_serve_from_another_thread_installs_no_handler() -> None:
    """Signal handlers only from the main thread: from another, serve installs none (and
    the target serves until its duration)."""
    before = {s: signal.getsignal(s) for s in _HANDLED}
    target = _Target([])
    seen: list[dict[int, Any]] = []
    result: list[int] = []

    def each() -> None:
        seen.append({s: signal.getsignal(s) for s in _HANDLED})

    t = threading.Thread(target=lambda: result.append(
        serve(target, target.stopping, duration=0.3, each=each)))
    t.start()
    t.join(30)
    assert result == [0] and target.stops == 1
    assert seen and all(s == before for s in seen)
