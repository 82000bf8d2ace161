"""systemd's ``sd_notify`` protocol, without a dependency.

A service started with ``Type=notify`` tells systemd that it is ready, that it is
alive (``WatchdogSec=``), that it reloads or stops, by sending short text
datagrams (``READY=1``, ``WATCHDOG=1``, ``RELOADING=1``, ``STOPPING=1``,
``STATUS=...``) to the unix datagram socket named in ``$NOTIFY_SOCKET``. A name
starting with ``@`` is in the abstract namespace (a leading NUL byte). Without
``$NOTIFY_SOCKET`` (not started by systemd) every call does nothing.

``$WATCHDOG_USEC`` (and ``$WATCHDOG_PID``, which must be this process when set) say
how often systemd expects ``WATCHDOG=1``; ping at half that interval::

    n = SystemdNotifier()
    n.ready("listening on can0")
    while running:
        if healthy:
            n.watchdog()
        time.sleep(n.watchdog_interval / 2)
"""

from __future__ import annotations

import logging
import os
import socket
import time
from collections.abc import Mapping

__all__ = ["SystemdNotifier", "notify"]

log = logging.getLogger(__name__)


def _address(name: str) -> str | bytes:
    if name.startswith("@"):
        return b"\0" + name[1:].encode()
    return name


class SystemdNotifier:
    """Sends ``sd_notify`` messages to ``$NOTIFY_SOCKET`` (or ``address``).

    :param address: the socket path (``@name``: abstract); default ``$NOTIFY_SOCKET``.
    :param environ: the environment to read (default ``os.environ``).

    ``enabled`` is False when there is no socket: every method then returns False.
    A failed send is logged once and returns False; it never raises, and never waits:
    when the socket's queue is full (nobody reads it) the message is dropped, so the
    daemon's threads cannot hang on it.
    """

    def __init__(self, address: str | None = None,
                 environ: Mapping[str, str] | None = None) -> None:
        env = os.environ if environ is None else environ
        self.address = address if address is not None else env.get("NOTIFY_SOCKET") or None
        usec = env.get("WATCHDOG_USEC", "")
        pid = env.get("WATCHDOG_PID", "")
        interval = None
        if usec.isdigit() and int(usec) > 0 and (not pid or pid == str(os.getpid())):
            interval = int(usec) / 1e6
        #: Seconds within which systemd expects ``WATCHDOG=1`` (None: no watchdog).
        self.watchdog_interval: float | None = interval
        self._sock: socket.socket | None = None
        self._warned = False

    @property
    def enabled(self) -> bool:
        return bool(self.address)

    def notify(self, state: str) -> bool:
        """Send one message (lines ``KEY=VALUE``); True when it was sent."""
        if not self.address:
            return False
        try:
            if self._sock is None:
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            self._sock.sendto(state.encode(), socket.MSG_DONTWAIT, _address(self.address))
            return True
        except BlockingIOError:
            if not self._warned:
                log.warning("sd_notify to %s: its queue is full (nobody reads it): "
                            "message dropped", self.address)
                self._warned = True
            return False
        except OSError as e:
            if not self._warned:
                log.warning("sd_notify to %s failed: %s", self.address, e)
                self._warned = True
            return False

    def ready(self, status: str | None = None) -> bool:
        """``READY=1``: start-up finished (systemd's ``Type=notify`` waits for it)."""
        return self.notify("READY=1" + (f"\nSTATUS={status}" if status else ""))

    def watchdog(self) -> bool:
        """``WATCHDOG=1``: still alive (send at least every ``watchdog_interval``)."""
        return self.notify("WATCHDOG=1")

    def reloading(self) -> bool:
        """``RELOADING=1`` with ``MONOTONIC_USEC`` (send :meth:`ready` when done)."""
        usec = time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000
        return self.notify(f"RELOADING=1\nMONOTONIC_USEC={usec}")

    def stopping(self) -> bool:
        """``STOPPING=1``: shutting down."""
        return self.notify("STOPPING=1")

    def status(self, text: str) -> bool:
        """``STATUS=...``: one line shown by ``systemctl status``."""
        return self.notify("STATUS=" + text.replace("\n", " "))

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None


def notify(state: str, environ: Mapping[str, str] | None = None) -> bool:
    """Send one ``sd_notify`` message to ``$NOTIFY_SOCKET``; False when there is none."""
    n = SystemdNotifier(environ=environ)
    try:
        return n.notify(state)
    finally:
        n.close()
