"""python-can's log writers on a file canrls opened itself (``canrls run --record``).

python-can opens a writer's file by name, following a link planted there; here the
file is opened by :func:`canrls.core.files.open_for_writing` (a regular file only, never
through a link) and handed to the writer of its suffix. Imports no numba (the daemon's
path).
"""

from __future__ import annotations

import contextlib
import io
import locale
import os
from pathlib import Path
from typing import BinaryIO

from can.io.generic import BinaryIOMessageWriter, MessageWriter, TextIOMessageWriter
from can.io.logger import MESSAGE_WRITERS

from canrls.core.errors import ConfigError
from canrls.core.files import check_writable, open_for_writing

__all__ = ["RECORD_SUFFIXES", "check_record_path", "open_writer", "writer_on"]

#: The formats a recording may have: those python-can writes to a file object and
#: canrls reads back.
RECORD_SUFFIXES = (".log", ".asc", ".blf", ".csv", ".trc")


def check_record_path(path: str | os.PathLike[str], what: str) -> Path:
    """``path`` if a recording can be written there (a known suffix, an existing
    directory, nothing but a regular file at the name); else :class:`ConfigError`."""
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix not in RECORD_SUFFIXES:
        raise ConfigError(f"{what}: unknown log format {suffix or '(no suffix)'!r} "
                          f"(a recording is {', '.join(RECORD_SUFFIXES)})")
    return check_writable(p, what, links=False)


def writer_on(f: BinaryIO, path: Path, what: str) -> MessageWriter:
    """python-can's writer of ``path``'s format (one of :data:`RECORD_SUFFIXES`) on the
    binary file ``f`` that canrls opened for it; the writer owns ``f`` (``stop()``
    closes it)."""
    cls = MESSAGE_WRITERS.get(path.suffix.lower()) if path.suffix.lower() in RECORD_SUFFIXES \
        else None
    if cls is None:
        raise ConfigError(f"{what}: unknown log format {path.suffix or '(no suffix)'!r} "
                          f"(canrls writes {', '.join(RECORD_SUFFIXES)})")
    with contextlib.suppress(AttributeError):
        f.raw.name = str(path)  # type: ignore[attr-defined]  # writers that print it
    if issubclass(cls, TextIOMessageWriter):
        return cls(file=io.TextIOWrapper(f, encoding=locale.getpreferredencoding(False)))
    if issubclass(cls, BinaryIOMessageWriter):
        return cls(file=f)
    raise ConfigError(f"{what}: python-can's writer of {path.suffix} takes no file object")


def open_writer(path: str | os.PathLike[str], what: str) -> MessageWriter:
    """python-can's writer of ``path``'s format, writing the file canrls opened."""
    p = check_record_path(path, what)
    f = open_for_writing(p, what)
    try:
        return writer_on(f, p, what)
    except BaseException:
        f.close()
        raise
