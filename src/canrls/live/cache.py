"""``[daemon] cache_dir``, applied before numba's kernels load.

numba fixes the cache directory of a compiled kernel when the module defining it is
imported, and the command line may import kernels before it parses its arguments. So
:func:`preload` looks for ``-C/--config FILE`` in the arguments first and, when that
file's ``[daemon]`` table names a ``cache_dir``, asks for the cache there
(:func:`canrls.prefer_cache_dir`: applied when numba loads, so the daemon, which runs
without numba, makes no directory; ``$NUMBA_CACHE_DIR`` set by the user still wins).
It imports nothing that imports numba. A file that cannot be read is left to the
configuration loader, which reports it properly.
"""

from __future__ import annotations

import argparse
import tomllib
from collections.abc import Sequence
from pathlib import Path

from canrls import prefer_cache_dir
from canrls.errors import CanrlsError
from canrls.files import MAX_CONFIG_BYTES, read_bytes
from canrls.live.settings import resolve_path

__all__ = ["configured_cache_dir", "preload"]


def configured_cache_dir(config: str | Path) -> Path | None:
    """``[daemon] cache_dir`` of the configuration file ``config`` (relative to the
    file's directory), or None (no such key, or a file that does not read)."""
    try:
        p = Path(config).expanduser()
        # a regular file of bounded size only: a FIFO must not block the start
        doc = tomllib.loads(read_bytes(p, str(p), limit=MAX_CONFIG_BYTES).decode("utf-8"))
    except (CanrlsError, OSError, ValueError, RecursionError):  # left to the loader
        return None
    table = doc.get("daemon")
    value = table.get("cache_dir") if isinstance(table, dict) else None
    if not isinstance(value, str) or not value or "\0" in value:
        return None
    return resolve_path(value, p.resolve().parent)


def preload(argv: Sequence[str]) -> Path | None:
    """Ask for ``[daemon] cache_dir`` of the ``-C/--config`` named in ``argv`` as numba's
    cache (:func:`canrls.prefer_cache_dir`); returns that directory (None: no such key)."""
    pre = argparse.ArgumentParser(add_help=False, allow_abbrev=False, exit_on_error=False)
    pre.add_argument("-C", "--config")
    try:
        known, _ = pre.parse_known_args(list(argv))
    except (argparse.ArgumentError, SystemExit):  # e.g. -C without a value: argparse says so
        return None
    if not known.config:
        return None
    d = configured_cache_dir(known.config)
    if d is not None:
        prefer_cache_dir(d)
    return d
