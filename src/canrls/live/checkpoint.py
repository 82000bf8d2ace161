"""Checkpoints of the live estimator: theta, P, the model and the counters, atomically.

File layout (``docs/daemon.md``)::

    CANRLS-CHECKPOINT\\n                      magic line
    {"format": "canrls.checkpoint/1", ...}\\n  header: one JSON line (format, canrls
                                              version, payload size, SHA-256 of the payload)
    <payload>                                 an uncompressed ``.npz`` archive (no pickles):
                                              ``__meta__`` = the JSON document (uint8), and
                                              one array per numpy array of the state

The JSON document holds everything that is not an array (models, settings
fingerprint, counters, scalars of the estimator states); each array is replaced by
``{"__array__": KEY}``. Floats go through JSON by ``repr``, which round-trips exactly,
so a restored estimator continues bit for bit.

Writing is atomic: the bytes go to a temporary file in the same directory, which is
flushed, ``fsync``-ed and renamed over the target (``os.replace``), then the
directory is ``fsync``-ed. A crash (``kill -9``, power loss) leaves either the old
or the new checkpoint, never a torn one.

Reading checks the magic, the format, the size and the checksum; anything else is a
:class:`~canrls.errors.CheckpointError`. :func:`set_aside` renames a bad file
(``NAME.bad-YYYYmmdd-HHMMSS``) so that it is kept for inspection but never loaded.

:class:`Checkpointer` is the daemon's use of them: resume at start (only under the
same configured model and :func:`fingerprint`), save every ``checkpoint_interval``
and at stop.
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import logging
import os
import time
import zipfile
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from canrls import __version__
from canrls.errors import CheckpointError, ConfigError
from canrls.estimation.model import Model
from canrls.estimation.pipeline import EstimatorSettings

__all__ = ["FORMAT", "MAGIC", "Checkpoint", "Checkpointer", "fingerprint", "save_checkpoint",
           "load_checkpoint", "set_aside"]

log = logging.getLogger(__name__)
T = TypeVar("T")

#: Format identifier in the header; another value is refused.
FORMAT = "canrls.checkpoint/1"
#: First line of every checkpoint file.
MAGIC = b"CANRLS-CHECKPOINT\n"
_MAX_HEADER = 4096


@dataclass
class Checkpoint:
    """What the daemon saves and resumes from.

    Attributes
    ----------
    model : the running model (``Model.to_dict()``; effects added by commands included)
    config_model : the model the configuration defined when the daemon started; a
        checkpoint resumes only under the same configured model
    fingerprint : what else must match to resume: estimator settings, sample period
    state : :meth:`canrls.estimation.pipeline.Pipeline.state` (theta, P, statistics, counts)
    counters : the daemon's counters (frames, commands, transmissions...)
    saved_at : wall-clock time of the save [s since the epoch]
    version : the canrls version that wrote it
    """

    model: dict[str, Any]
    config_model: dict[str, Any]
    fingerprint: dict[str, Any]
    state: dict[str, Any]
    counters: dict[str, int] = field(default_factory=dict)
    saved_at: float = 0.0
    version: str = __version__


# ------------------------------------------------------------------ (de)serialise
def _flatten(obj: Any, arrays: dict[str, np.ndarray], path: str) -> Any:
    if isinstance(obj, np.ndarray):
        key = f"a{len(arrays)}"
        arrays[key] = obj
        return {"__array__": key}
    if isinstance(obj, Mapping):
        if set(obj) == {"__array__"}:
            raise CheckpointError(f"checkpoint: reserved key __array__ at {path or '/'}")
        out = {}
        for k, v in obj.items():
            if not isinstance(k, str):
                raise CheckpointError(f"checkpoint: key {k!r} at {path or '/'} is not a string")
            out[k] = _flatten(v, arrays, f"{path}/{k}")
        return out
    if isinstance(obj, list | tuple):
        return [_flatten(v, arrays, f"{path}/{i}") for i, v in enumerate(obj)]
    if isinstance(obj, np.generic):
        return obj.item()
    if obj is None or isinstance(obj, bool | int | float | str):
        return obj
    raise CheckpointError(f"checkpoint: cannot store {type(obj).__name__} at {path or '/'}")


def _unflatten(obj: Any, arrays: Mapping[str, np.ndarray]) -> Any:
    if isinstance(obj, dict):
        if set(obj) == {"__array__"}:
            key = obj["__array__"]
            if key not in arrays:
                raise CheckpointError(f"checkpoint: array {key!r} missing from the payload")
            return arrays[key]
        return {k: _unflatten(v, arrays) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_unflatten(v, arrays) for v in obj]
    return obj


def _encode(cp: Checkpoint) -> bytes:
    arrays: dict[str, np.ndarray] = {}
    doc = _flatten({"model": cp.model, "config_model": cp.config_model,
                    "fingerprint": cp.fingerprint, "state": cp.state,
                    "counters": cp.counters, "saved_at": cp.saved_at,
                    "version": cp.version}, arrays, "")
    meta = json.dumps(doc, sort_keys=True, allow_nan=True).encode()
    buf = io.BytesIO()
    np.savez(buf, __meta__=np.frombuffer(meta, np.uint8), **arrays)
    payload = buf.getvalue()
    header = json.dumps({"format": FORMAT, "canrls": cp.version, "size": len(payload),
                         "sha256": hashlib.sha256(payload).hexdigest()}, sort_keys=True)
    return MAGIC + header.encode() + b"\n" + payload


def _decode(raw: bytes, source: str) -> Checkpoint:
    if not raw.startswith(MAGIC):
        raise CheckpointError(f"{source}: not a canrls checkpoint (bad magic)")
    end = raw.find(b"\n", len(MAGIC), len(MAGIC) + _MAX_HEADER)
    if end < 0:
        raise CheckpointError(f"{source}: checkpoint header is missing or too long")
    try:
        header = json.loads(raw[len(MAGIC):end])
    except (ValueError, UnicodeDecodeError) as e:
        raise CheckpointError(f"{source}: checkpoint header is not JSON: {e}") from e
    if not isinstance(header, dict):
        raise CheckpointError(f"{source}: checkpoint header is not a JSON object")
    fmt = header.get("format")
    if fmt != FORMAT:
        raise CheckpointError(f"{source}: checkpoint format {fmt!r}, this canrls reads "
                              f"{FORMAT!r}")
    payload = raw[end + 1:]
    if header.get("size") != len(payload):
        raise CheckpointError(f"{source}: checkpoint payload is {len(payload)} bytes, header "
                              f"says {header.get('size')!r} (truncated?)")
    digest = hashlib.sha256(payload).hexdigest()
    if header.get("sha256") != digest:
        raise CheckpointError(f"{source}: checkpoint checksum mismatch (header "
                              f"{header.get('sha256')!r}, payload {digest})")
    try:
        with np.load(io.BytesIO(payload), allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        meta = json.loads(arrays.pop("__meta__").tobytes())
    except (ValueError, KeyError, OSError, zipfile.BadZipFile) as e:
        raise CheckpointError(f"{source}: checkpoint payload unreadable: {e}") from e
    doc = _unflatten(meta, arrays)
    try:
        return Checkpoint(model=doc["model"], config_model=doc["config_model"],
                          fingerprint=doc["fingerprint"], state=doc["state"],
                          counters={k: int(v) for k, v in doc["counters"].items()},
                          saved_at=float(doc["saved_at"]), version=str(doc["version"]))
    except (KeyError, TypeError, ValueError, AttributeError) as e:
        raise CheckpointError(f"{source}: checkpoint lacks or garbles {e}") from e


# ------------------------------------------------------------------ files
def save_checkpoint(path: str | os.PathLike[str], cp: Checkpoint) -> int:
    """Write ``cp`` to ``path`` atomically (temporary file, fsync, rename); returns bytes.

    :raises CheckpointError: the state holds something that cannot be stored.
    :raises OSError: the file system refused.
    """
    p = Path(path)
    data = _encode(cp)
    tmp = p.with_name(f".{p.name}.tmp.{os.getpid()}")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_CLOEXEC, 0o644)
    try:
        view = memoryview(data)
        while view:
            n = os.write(fd, view)
            view = view[n:]
        os.fsync(fd)
    except BaseException:
        os.close(fd)
        tmp.unlink(missing_ok=True)
        raise
    os.close(fd)
    os.replace(tmp, p)
    try:  # make the rename itself durable
        dfd = os.open(p.parent, os.O_RDONLY | os.O_DIRECTORY)
    except OSError:  # pragma: no cover - e.g. a platform without directory fds
        return len(data)
    try:
        os.fsync(dfd)
    finally:
        os.close(dfd)
    return len(data)


def load_checkpoint(path: str | os.PathLike[str]) -> Checkpoint:
    """Read and verify a checkpoint (magic, format, size, SHA-256).

    :raises CheckpointError: the file is not a valid checkpoint.
    :raises FileNotFoundError: there is none.
    """
    p = Path(path)
    return _decode(p.read_bytes(), str(p))


def set_aside(path: str | os.PathLike[str]) -> Path:
    """Rename a bad checkpoint to ``NAME.bad-YYYYmmdd-HHMMSS[-N]``; returns the new path."""
    p = Path(path)
    stamp = time.strftime("%Y%m%d-%H%M%S")
    target = p.with_name(f"{p.name}.bad-{stamp}")
    k = 1
    while target.exists():
        target = p.with_name(f"{p.name}.bad-{stamp}-{k}")
        k += 1
    os.replace(p, target)
    return target


# ------------------------------------------------------------------ the daemon's use
def _plain(d: Any) -> Any:
    """A JSON round trip: tuples become lists, as a checkpoint stores them."""
    return json.loads(json.dumps(d, allow_nan=True))


def fingerprint(settings: EstimatorSettings, dt: float) -> dict[str, Any]:
    """What besides the model must match for a checkpoint to resume: ``dt`` and every
    estimator setting (the forgetting factor too: ``set_lambda`` lives in the state)."""
    d: dict[str, Any] = {"dt": dt}
    for f in dataclasses.fields(settings):
        v = getattr(settings, f.name)
        if isinstance(v, Mapping):
            v = {str(k): repr(x) for k, x in sorted(v.items())}
        elif not (v is None or isinstance(v, bool | int | float | str)):
            v = repr(v)
        d[f.name] = v
    return _plain(d)


class Checkpointer:
    """Resume from and save to one checkpoint file, periodically.

    :param path: the checkpoint file (``[daemon] checkpoint``; None: no checkpoints).
    :param config_model: the model the configuration defines; a checkpoint resumes
        only under the same one.
    :param settings, dt: the estimator settings and sample period (:func:`fingerprint`).
    :param interval: seconds between periodic saves.
    """

    def __init__(self, path: Path | None, config_model: Model, settings: EstimatorSettings,
                 dt: float, interval: float) -> None:
        self.path = path
        self.config_model = config_model
        self.fingerprint = fingerprint(settings, dt)
        self.interval = interval
        self.next_at = 0.0
        #: checkpoints written
        self.saved = 0

    def resume(self, restore: Callable[[Model, dict[str, Any]], T]
               ) -> tuple[T, Checkpoint] | None:
        """Load the checkpoint and rebuild from it: ``restore(model, state)``.

        None when there is none, or when it does not fit (another configured model,
        other settings, a damaged file, a state ``restore`` refuses): such a file is
        set aside (:func:`set_aside`) and the estimator starts from the prior.
        """
        path = self.path
        if path is None:
            return None
        if not path.exists():
            log.info("no checkpoint at %s: starting from the prior", path)
            return None
        try:
            cp = load_checkpoint(path)
            if cp.config_model != _plain(self.config_model.to_dict()):
                raise CheckpointError(f"{path}: checkpoint was taken with another configured "
                                      f"model ({cp.config_model.get('effects')})")
            mine = self.fingerprint
            if cp.fingerprint != mine:
                diff = sorted(k for k in set(cp.fingerprint) | set(mine)
                              if cp.fingerprint.get(k) != mine.get(k))
                raise CheckpointError(f"{path}: checkpoint was taken with other estimator "
                                      f"settings ({', '.join(diff)})")
            model = Model.from_dict(cp.model, source=f"{path} (checkpoint)",
                                    available_signals=self.config_model.available_signals)
            restored = restore(model, cp.state)
        except (CheckpointError, ConfigError, KeyError, ValueError, TypeError, IndexError) as e:
            where = set_aside(path)
            log.error("checkpoint %s not loaded (%s); set aside as %s", path, e, where)
            return None
        log.info("resumed from checkpoint %s (%d samples, effects %s, saved %s)", path,
                 int(cp.state.get("samples", 0)), ",".join(model.effect_names),
                 time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(cp.saved_at)))
        return restored, cp

    def due(self, now: float) -> bool:
        return now >= self.next_at

    def save(self, model: Model, state: dict[str, Any], counters: dict[str, int]) -> Path | None:
        """Write a checkpoint now (None: no checkpoint file configured, or it could not
        be written: logged, the daemon goes on)."""
        path = self.path
        if path is None:
            return None
        cp = Checkpoint(model=_plain(model.to_dict()),
                        config_model=_plain(self.config_model.to_dict()),
                        fingerprint=self.fingerprint, state=state, counters=counters,
                        saved_at=time.time())
        try:
            save_checkpoint(path, cp)
        except OSError as e:
            log.error("checkpoint %s: cannot write: %s", path, e)
            return None
        self.saved += 1
        log.debug("checkpoint written to %s", path)
        return path
