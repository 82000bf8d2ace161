"""Interpreter settings for latency while at least one daemon runs."""

from __future__ import annotations

import gc
import sys
import threading

__all__ = ["InterpreterTuning", "interpreter"]


class InterpreterTuning:
    """Process-wide settings for latency while at least one daemon runs.

    * The bus reader (:class:`canrls.live.bus_link.BusReader`) and the estimator share the GIL.
      With CPython's default switch interval (5 ms) a thread that is ready waits up
      to 5 ms while another runs Python code without blocking, e.g. the reader
      taking frames already queued by python-can's virtual bus. ``switch_interval``
      (``sys.setswitchinterval``) shortens that wait.
    * ``gc.freeze()`` moves every object alive at start (imported modules, the
      DBC encoders) out of the cyclic collector's reach, so an
      occasional full collection no longer costs tens of milliseconds.

    The first daemon to start applies them, the last to stop restores the
    interpreter's settings (``gc.unfreeze()``).
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._users = 0
        self._saved = 0.0

    def tune(self, switch_interval: float) -> None:
        with self._lock:
            self._users += 1
            if self._users == 1:
                self._saved = sys.getswitchinterval()
                if switch_interval > 0:
                    sys.setswitchinterval(switch_interval)
                gc.freeze()

    def restore(self) -> None:
        with self._lock:
            self._users -= 1
            if self._users == 0:
                sys.setswitchinterval(self._saved)
                gc.unfreeze()


#: the one instance of the process
interpreter = InterpreterTuning()
