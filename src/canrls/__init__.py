"""canrls: identify the physics of an electric drive online, over CAN.

The package is layered so that dependencies run one way::

    bus, codec, log readers (edges)  ->  pipeline (pure)  <-  effects, model, rls, fixed

The daemon (``canrls run``) and the offline replay (``canrls fit``) call the same
pipeline, so a replayed log gives the same parameters as the live run, bit for bit.

The daemon's per-frame work runs in C extensions and numpy, without a JIT compiler.
The offline commands' kernels that numba compiles are cached in the user's cache
directory (:func:`use_cache_dir`), chosen when numba is first imported: importing
canrls writes nothing, and nothing is written into the installed package.
"""

from __future__ import annotations

import atexit
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING

from canrls.errors import CanrlsError

if TYPE_CHECKING:  # importlib.abc costs 30 ms: not before canrls run's signal handlers
    import importlib.machinery

__version__ = "0.1.0"

__all__ = ["CanrlsError", "__version__", "prefer_cache_dir", "use_cache_dir"]

#: ``$NUMBA_CACHE_DIR`` as the user set it before canrls was imported ("": not set)
_USER_CACHE_DIR = os.environ.get("NUMBA_CACHE_DIR", "")
#: the temporary fallback of this process, made at most once
_temp_cache: Path | None = None
#: the directory :func:`prefer_cache_dir` asked for (None: the default)
_preferred: Path | None = None


def _usable(d: Path) -> bool:
    """``d`` exists (made if needed) and this process may write into it."""
    try:
        d.mkdir(parents=True, exist_ok=True)
    except OSError:
        return False
    return os.access(d, os.W_OK | os.X_OK)


def _temporary() -> Path:
    import shutil
    import tempfile

    global _temp_cache
    if _temp_cache is None:
        _temp_cache = Path(tempfile.mkdtemp(prefix="canrls-numba-"))  # mode 0700
        atexit.register(shutil.rmtree, _temp_cache, ignore_errors=True)
    return _temp_cache


def use_cache_dir(path: str | os.PathLike[str] | None = None) -> Path | None:
    """Point numba's cache of compiled kernels away from the installed package.

    The directory is ``$NUMBA_CACHE_DIR`` if the user set it (left as it is); else
    ``path`` (``[daemon] cache_dir``); else ``$XDG_CACHE_HOME/canrls/numba`` or
    ``~/.cache/canrls/numba``. One that cannot be made or written (a read-only home, a
    hardened systemd unit) gives way to a fresh temporary directory, removed at exit,
    so that every command starts. Returns the directory (None: no temporary directory
    could be made either; numba then decides).

    numba fixes a kernel's cache directory when the kernel's module is imported, so
    this runs when canrls is imported; ``canrls`` applies ``[daemon] cache_dir`` of
    ``--config`` before the kernels load (:mod:`canrls.live.cache`). A later call
    affects the kernels imported after it.
    """
    if _USER_CACHE_DIR:
        return Path(_USER_CACHE_DIR)
    if path is not None:
        d = Path(path).expanduser()
    else:
        xdg = os.environ.get("XDG_CACHE_HOME", "")
        try:
            base = Path(xdg) if os.path.isabs(xdg) else Path("~/.cache").expanduser()
        except RuntimeError:  # no home directory at all
            base = Path("/nonexistent")
        d = base / "canrls" / "numba"
    if not _usable(d):
        try:
            d = _temporary()
        except OSError:
            return None
    os.environ["NUMBA_CACHE_DIR"] = str(d)
    if "numba" in sys.modules:  # already imported: numba re-reads its environment
        from numba.core.config import reload_config

        reload_config()
    return d


def prefer_cache_dir(path: str | os.PathLike[str] | None) -> Path | None:
    """Cache numba's kernels in ``path`` (None: the default of :func:`use_cache_dir`).

    Applied when numba is first imported, so a process that never imports it (the
    daemon) makes no directory at all; at once (returning :func:`use_cache_dir`'s
    answer) when numba is already loaded. Returns None when deferred.
    """
    global _preferred
    _preferred = None if path is None else Path(path).expanduser()
    if "numba" in sys.modules:
        return use_cache_dir(_preferred)
    return None


class _NumbaCacheHook:
    """Runs :func:`use_cache_dir` right before the first import of numba (numba reads
    ``$NUMBA_CACHE_DIR`` when it loads), then gets out of the way: it finds nothing
    itself (a meta path finder: ``find_spec`` is all ``sys.meta_path`` asks of it)."""

    done = False

    def find_spec(self, fullname: str, path: Sequence[str] | None = None,
                  target: ModuleType | None = None) -> importlib.machinery.ModuleSpec | None:
        if fullname == "numba" and not self.done:
            self.done = True
            use_cache_dir(_preferred)
        return None


if "numba" in sys.modules:  # imported before canrls
    use_cache_dir()
elif not any(isinstance(f, _NumbaCacheHook) for f in sys.meta_path):
    sys.meta_path.insert(0, _NumbaCacheHook())
