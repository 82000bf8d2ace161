"""What the fault tests share for calls that may hang on a FIFO: run the call in a
thread, and if it blocks, free it so that the test fails instead of hanging."""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any


def in_thread(fn: Callable[[], Any], unblock: Callable[[], None], what: str) -> Any:
    """``fn()`` in a thread; if it is still blocked after 30 s (a hang: the fault),
    ``unblock()`` frees it and the test fails saying it blocked on ``what``."""
    out: dict[str, Any] = {}

    def target() -> None:
        try:
            out["value"] = fn()
        except BaseException as e:  # re-raised below
            out["error"] = e

    t = threading.Thread(target=target, name=f"blocking {what}")
    t.start()
    t.join(30)
    hung = t.is_alive()
    if hung:
        unblock()
        t.join(30)
    assert not hung, f"blocked on {what}"
    if "error" in out:
        raise out["error"]
    return out.get("value")


def unblock_fifo(fifo: Path) -> Callable[[], None]:
    """A writer that opens ``fifo`` and closes it: a reader blocked on it sees EOF."""
    def unblock() -> None:
        os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
    return unblock
