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
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import time
import zipfile
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from canrls import __version__
from canrls.errors import CheckpointError

__all__ = ["FORMAT", "MAGIC", "Checkpoint", "save_checkpoint", "load_checkpoint", "set_aside"]

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
