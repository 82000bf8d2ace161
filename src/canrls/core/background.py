"""A call run in a thread of its own while the caller goes on: the overlap of the C kernels,
which release the GIL (the candump reader's next block, the fixed-point estimator)."""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any, Generic, TypeVar

__all__ = ["Background"]

_T = TypeVar("_T")


class Background(Generic[_T]):
    """``fn(*args)`` started in a thread; :meth:`result` waits for it and returns its value
    or raises its exception in the caller. The thread ends with the call (nothing waits in
    it afterwards), so a result never asked for holds no thread."""

    def __init__(self, fn: Callable[..., _T], *args: Any, name: str = "canrls worker") -> None:
        self._fn = fn
        self._args = args
        self._value: Any = None
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            self._value = self._fn(*self._args)
        except BaseException as e:  # handed to the caller by result()
            self._error = e

    def join(self) -> None:
        """Wait for the call to end (its value or exception kept for :meth:`result`)."""
        self._thread.join()

    def result(self) -> _T:
        """The call's value (after waiting for it), or its exception raised here."""
        self._thread.join()
        if self._error is not None:
            raise self._error
        return self._value
