"""The recording of every frame received (``[daemon] record``, ``canrls run --record``).

Recording is not the bus: :class:`Recorder` keeps the python-can writer's errors (a
full disk, ``EFBIG``, a file system gone read-only) to itself: the first is logged once
and counted, the recording stops there (the file keeps what was written), and
estimation and publication go on (docs/reliability.md).
"""

from __future__ import annotations

import logging
import os
import threading

import can

__all__ = ["Recorder"]

log = logging.getLogger(__name__)


class Recorder(can.Listener):
    """Passes every frame to a python-can writer until the writer fails.

    :param writer: the python-can writer (``can.Logger(path)``).
    :param path: the file it writes, for the log line.
    """

    def __init__(self, writer: can.Listener, path: str | os.PathLike[str]) -> None:
        self._writer: can.Listener | None = writer
        self.path = str(path)
        #: frames handed to the writer
        self.frames = 0
        #: frames not recorded because the recording had stopped on an error
        self.dropped = 0
        #: I/O errors of the writer (the first stops the recording; a second can come
        #: from closing it)
        self.errors = 0
        #: the first error, in words (None: none)
        self.error: str | None = None
        self._lock = threading.Lock()

    @property
    def recording(self) -> bool:
        """Whether frames are still written."""
        return self._writer is not None

    def on_message_received(self, msg: can.Message) -> None:
        w = self._writer
        if w is None:
            self.dropped += 1
            return
        try:
            w.on_message_received(msg)
        except (OSError, ValueError) as e:  # ValueError: a write to a file closed under it
            self.dropped += 1
            self._failed(e)
            return
        self.frames += 1

    def stop(self) -> None:
        """Close the writer (its last buffered frames go to the file); an error in doing
        so is logged and counted like any other."""
        with self._lock:
            w, self._writer = self._writer, None
        if w is None:
            return
        try:
            w.stop()
        except (OSError, ValueError) as e:
            self._failed(e)

    def _failed(self, e: BaseException) -> None:
        """The writer failed: counted, logged once, the recording stopped."""
        self.errors += 1
        if self.error is None:
            self.error = f"{type(e).__name__}: {e}"
            log.error("recording to %s stopped after %d frames: %s (estimation and "
                      "publication go on)", self.path, self.frames, e)
        with self._lock:
            w, self._writer = self._writer, None
        if w is not None:
            try:
                w.stop()  # what the file keeps is what was written before the error
            except (OSError, ValueError):
                pass

    def stats(self) -> dict[str, object]:
        """``{"path", "frames", "dropped", "errors", "error"}`` (``canrls run --json``)."""
        return {"path": self.path, "frames": self.frames, "dropped": self.dropped,
                "errors": self.errors, "error": self.error}
