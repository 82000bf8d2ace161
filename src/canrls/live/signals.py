"""Signal handlers that take no lock: the action runs in a thread of its own.

A Python signal handler runs in the main thread between two bytecodes, also inside a
lock the main thread holds (an ``Event``'s, a logging handler's) and inside another
handler. One that sets an event or logs can therefore wait on itself for ever, and each
further signal nests another handler in that wait. :class:`SignalRelay`'s handlers only
write the signal's number to a pipe; its thread reads the pipe and calls the action.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import threading
from collections.abc import Callable, Mapping
from types import TracebackType
from typing import Any

__all__ = ["SignalRelay"]

log = logging.getLogger(__name__)


class SignalRelay:
    """Handlers for ``actions``' signals while in the ``with`` block (main thread only;
    elsewhere nothing is installed); ``actions[signum](signum)`` is called in the relay's
    thread, once per signal received, in their order. The previous handlers (or those
    given to :meth:`leave`) are put back at the end, then the signals already received
    are acted on before the block exits.
    """

    def __init__(self, actions: Mapping[int, Callable[[int], None]]) -> None:
        self.actions = dict(actions)
        self._old: dict[int, Any] = {}
        self._fds: tuple[int, int] | None = None
        self._thread: threading.Thread | None = None

    def _handler(self, signum: int, frame: Any) -> None:
        # no lock, no logging, no raising: one byte to the pipe (full: signals are
        # already waiting to be acted on, so this one adds nothing)
        fds = self._fds
        if fds is not None:
            with contextlib.suppress(BlockingIOError):
                os.write(fds[1], bytes([signum]))

    def _relay(self, fd: int) -> None:
        while data := os.read(fd, 256):
            for signum in data:
                try:
                    self.actions[signum](signum)
                except Exception:  # the next signal must still be acted on
                    log.exception("signal %d: its action failed", signum)

    @property
    def previous(self) -> dict[int, Any]:
        """The handlers the relay replaced (empty: none installed)."""
        return dict(self._old)

    def leave(self, sig: int, handler: Any) -> None:
        """At the end, install ``handler`` for ``sig`` instead of the previous one."""
        if sig in self._old:
            self._old[sig] = handler

    def __enter__(self) -> SignalRelay:
        if threading.current_thread() is not threading.main_thread():
            return self
        r, w = os.pipe2(os.O_CLOEXEC)
        os.set_blocking(w, False)
        self._fds = (r, w)
        self._thread = threading.Thread(target=self._relay, args=(r,), daemon=True,
                                        name="canrls signals")
        self._thread.start()
        for sig in self.actions:
            self._old[sig] = signal.signal(sig, self._handler)
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if self._fds is None or self._thread is None:
            return
        for sig, old in self._old.items():
            signal.signal(sig, old)
        self._old.clear()
        r, w = self._fds
        os.close(w)  # the relay reads what is left, then the end of the pipe
        self._thread.join()
        os.close(r)
        self._fds = self._thread = None
