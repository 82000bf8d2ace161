"""The signals of ``canrls run`` from its first moment, before the heavy imports.

:func:`install` runs first thing in :func:`canrls.cli.main.main`: until the command
installs its own handlers, a SIGTERM or SIGINT is remembered (:func:`stop_requested`:
the daemon then starts and stops at once) and a SIGHUP ignored (docs/daemon.md).
"""

from __future__ import annotations

import signal
import threading
from typing import Any

__all__ = ["HANDLED", "install", "previous_handlers", "stop_requested"]

#: The signals handled from the first moment.
HANDLED = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)

_previous: dict[int, Any] = {}
_stop: list[int] = []


def _remember(signum: int, frame: Any) -> None:
    if signum != signal.SIGHUP:
        _stop.append(signum)


def install() -> bool:
    """Remember stops and ignore SIGHUP from now on (main thread only; once). True when
    the handlers are in place."""
    if threading.current_thread() is not threading.main_thread():
        return False
    if not _previous:
        for sig in HANDLED:
            _previous[sig] = signal.signal(sig, _remember)
    return True


def stop_requested() -> int | None:
    """The first SIGTERM or SIGINT received since :func:`install` (None: none)."""
    return _stop[0] if _stop else None


def previous_handlers() -> dict[int, Any]:
    """The handlers :func:`install` replaced (empty: it did not run): what the command
    restores at its end."""
    return dict(_previous)
