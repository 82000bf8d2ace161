"""Checkpoints of the live estimator: theta, P, the model and the counters, atomically.

A checkpoint is a magic line, a JSON header (format, version, size, SHA-256) and an
uncompressed ``.npz`` archive without pickles; floats round-trip exactly, so a restored
estimator continues bit for bit. The file is opened as a database opens its files:
never through a link, bounded, checked before it is trusted, written atomically and
privately. :class:`Checkpointer` is the daemon's use of them. The format and every
promise: docs/daemon.md, "Checkpoints".
"""

from __future__ import annotations

import dataclasses
import errno
import fcntl
import hashlib
import io
import json
import logging
import math
import os
import re
import secrets
import stat
import time
import tokenize
import weakref
import zipfile
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from canrls import __version__
from canrls.core.checks import is_positive, is_real
from canrls.core.errors import CheckpointError, ConfigError
from canrls.estimation.model import Model
from canrls.estimation.settings import EstimatorSettings

__all__ = ["FORMAT", "MAGIC", "MAX_BYTES", "MAX_DEPTH", "MAX_PARAMETERS", "Checkpoint",
           "CheckpointInUseError", "CheckpointPathError", "Checkpointer", "CheckpointLock",
           "clean_temporaries", "fingerprint", "save_checkpoint", "load_checkpoint",
           "set_aside"]

log = logging.getLogger(__name__)
T = TypeVar("T")

#: Format identifier in the header; another value is refused.
FORMAT = "canrls.checkpoint/1"
#: First line of every checkpoint file.
MAGIC = b"CANRLS-CHECKPOINT\n"
_MAX_HEADER = 4096
#: Largest checkpoint file read or written [bytes] (n = 256 parameters and a calibration
#: window of 10 s at 20 kHz take about 10 MB).
MAX_BYTES = 64 * 2**20
#: Deepest nesting of the JSON document (a checkpoint of today's states has 7 levels).
MAX_DEPTH = 32
#: Most parameters of a checkpointed model: the ``Index`` and ``Count`` of the
#: parameter frames (RlsEstimate, RlsSigma, RlsReference, RlsParamInfo) are 8 bits
#: (the daemon passes its ``[daemon] max_parameters``, at most this).
MAX_PARAMETERS = 255
#: Subtrees of the state that hold recorded samples, where NaN (a gap) is data.
_SAMPLE_KEYS = frozenset({"window", "tail", "calibration"})
_MODE = 0o600
_O_CLOEXEC = getattr(os, "O_CLOEXEC", 0)
_O_NOFOLLOW = getattr(os, "O_NOFOLLOW", 0)
_O_NONBLOCK = getattr(os, "O_NONBLOCK", 0)
_O_DIRECTORY = getattr(os, "O_DIRECTORY", 0)
_ARRAY_NAME = re.compile(r"a\d{1,9}\Z")


class CheckpointPathError(CheckpointError):
    """The checkpoint's name or directory cannot be used: a symbolic link, a directory, a
    FIFO or a device at the name, or a directory that is missing or refuses writes.
    Such a path is never renamed, read or written through."""


class CheckpointInUseError(CheckpointError):
    """Another process holds the checkpoint's lock (``NAME.lock``): a second daemon on
    one checkpoint file is refused at start."""


class CheckpointLock:
    """``flock`` on ``NAME.lock`` beside the checkpoint, held while the daemon runs.

    Opened relative to the directory's descriptor with ``O_NOFOLLOW`` (a link at the
    lock's name is refused, never followed), mode 0600, the holder's PID written in it.
    The lock is the open file's: it goes with :meth:`release`, the object, or the
    process (a ``kill -9`` leaves no stale lock; the file itself stays, harmless).

    :raises CheckpointInUseError: another process holds it (names the path and its PID).
    :raises CheckpointPathError: the lock file cannot be made or is not a regular file.
    """

    def __init__(self, path: Path) -> None:
        self.path = path.with_name(path.name + ".lock")
        with _directory(path) as dfd:
            st = _lstat(dfd, self.path.name)
            if st is not None and not stat.S_ISREG(st.st_mode):  # not opened: a device acts
                raise CheckpointPathError(f"{path}: the checkpoint's lock {self.path} is "
                                          f"{_kind(st.st_mode)}, not a regular file; it is "
                                          f"left untouched")
            try:
                fd = os.open(self.path.name, os.O_RDWR | os.O_CREAT | _O_NOFOLLOW
                             | _O_NONBLOCK | _O_CLOEXEC, _MODE, dir_fd=dfd)
            except OSError as e:
                st = _lstat(dfd, self.path.name)
                kind = "" if st is None or stat.S_ISREG(st.st_mode) else f" ({_kind(st.st_mode)})"
                raise CheckpointPathError(f"{path}: cannot open the checkpoint's lock "
                                          f"{self.path}{kind}: {e.strerror}") from e
        try:
            st = os.fstat(fd)
            if not stat.S_ISREG(st.st_mode):
                raise CheckpointPathError(f"{path}: the checkpoint's lock {self.path} is "
                                          f"{_kind(st.st_mode)}, not a regular file")
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = os.pread(fd, 32, 0).decode("ascii", "replace").strip()
                pid = holder if holder.isdigit() else "unknown"
                raise CheckpointInUseError(
                    f"{path}: the checkpoint is in use by another canrls daemon (PID {pid}, "
                    f"lock {self.path}); two daemons must not share one checkpoint file: "
                    f"give each its own [daemon] checkpoint") from None
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode("ascii"), 0)
        except BaseException:
            os.close(fd)
            raise
        self._fd: int | None = fd
        self._finalizer = weakref.finalize(self, os.close, fd)

    def release(self) -> None:
        """Release the lock (idempotent)."""
        if self._fd is not None:
            self._fd = None
            self._finalizer()


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


def _unflatten(obj: Any, arrays: Mapping[str, np.ndarray], used: set[str]) -> Any:
    if isinstance(obj, dict):
        if set(obj) == {"__array__"}:
            key = obj["__array__"]
            if not isinstance(key, str) or key not in arrays:
                raise CheckpointError(f"array {key!r} missing from the payload")
            if key in used:
                raise CheckpointError(f"array {key!r} referenced twice")
            used.add(key)
            return arrays[key]
        return {k: _unflatten(v, arrays, used) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_unflatten(v, arrays, used) for v in obj]
    return obj


_JSON_STRING = re.compile(rb'"(?:[^"\\]|\\.)*"', re.DOTALL)
_BRACKET = re.compile(rb"[\[\]{}]")


def _json_depth(text: bytes) -> int:
    """Deepest nesting of ``[`` and ``{`` in JSON text (strings skipped), found without
    recursion, so that a deep document is refused before the parser recurses into it."""
    depth = deepest = 0
    for m in _BRACKET.finditer(_JSON_STRING.sub(b'""', text)):
        if m.group() in b"[{":
            depth += 1
            deepest = max(deepest, depth)
        else:
            depth -= 1
    return deepest


def _json(text: bytes, what: str) -> Any:
    if _json_depth(text) > MAX_DEPTH:
        raise CheckpointError(f"{what} nests deeper than {MAX_DEPTH} levels")
    try:
        return json.loads(text)
    except (ValueError, UnicodeDecodeError, RecursionError) as e:
        raise CheckpointError(f"{what} is not JSON: {e}") from e


def _read_arrays(payload: bytes) -> dict[str, np.ndarray]:
    """The members of the ``.npz`` payload, each ``.npy`` header checked against the
    member's stored size before the array is allocated."""
    arrays: dict[str, np.ndarray] = {}
    with zipfile.ZipFile(io.BytesIO(payload)) as zf:
        infos = zf.infolist()
        if len(infos) > len(payload) // 22 + 1:  # 22 bytes: the smallest zip entry
            raise CheckpointError("too many archive members")
        for info in infos:
            name = info.filename
            key = name[:-4] if name.endswith(".npy") else ""
            if key != "__meta__" and not _ARRAY_NAME.match(key):
                raise CheckpointError(f"unexpected archive member {name!r}")
            if key in arrays:
                raise CheckpointError(f"archive member {name!r} twice")
            if info.compress_type != zipfile.ZIP_STORED or info.file_size > len(payload):
                raise CheckpointError(f"archive member {name!r} is compressed or larger "
                                      f"than the file")
            with zf.open(info) as f:
                version = np.lib.format.read_magic(f)
                if version == (1, 0):
                    shape, fortran, dtype = np.lib.format.read_array_header_1_0(f)
                elif version == (2, 0):
                    shape, fortran, dtype = np.lib.format.read_array_header_2_0(f)
                else:
                    raise CheckpointError(f"archive member {name!r}: .npy version {version}")
                if dtype.kind not in "biuf" or dtype.hasobject or len(shape) > 2:
                    raise CheckpointError(f"archive member {name!r}: {dtype} array of "
                                          f"{len(shape)} dimensions")
                if math.prod(shape) * dtype.itemsize > info.file_size:
                    raise CheckpointError(f"archive member {name!r}: shape {shape} is larger "
                                          f"than the member")
            with zf.open(info) as f:
                arrays[key] = np.lib.format.read_array(f, allow_pickle=False)
    return arrays


def _check_values(obj: Any, path: str, samples: bool) -> None:
    """JSON types and numeric arrays only; no NaN, and no infinity in an array, outside
    the recorded samples (``samples``)."""
    if isinstance(obj, dict):
        for k, v in obj.items():
            _check_values(v, f"{path}/{k}", samples or k in _SAMPLE_KEYS)
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            _check_values(v, f"{path}/{i}", samples)
    elif isinstance(obj, np.ndarray):
        if not samples and obj.dtype.kind == "f" and not np.isfinite(obj).all():
            raise CheckpointError(f"{path or '/'} holds NaN or infinity")
    elif isinstance(obj, float):
        if not samples and math.isnan(obj):
            raise CheckpointError(f"{path or '/'} is NaN")
    elif not (obj is None or isinstance(obj, bool | int | str)):  # pragma: no cover - JSON
        raise CheckpointError(f"{path or '/'}: {type(obj).__name__}")


def _plain_json(obj: Any, path: str) -> None:
    """``obj`` holds no array (a model, a fingerprint: JSON only)."""
    if isinstance(obj, np.ndarray):
        raise CheckpointError(f"{path} is an array")
    if isinstance(obj, dict):
        for k, v in obj.items():
            _plain_json(v, f"{path}/{k}")
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            _plain_json(v, f"{path}/{i}")


def _document(doc: Any) -> Checkpoint:
    """The fields of a :class:`Checkpoint`, each of its type."""
    if not isinstance(doc, dict):
        raise CheckpointError("the document is not an object")
    fields = {f.name for f in dataclasses.fields(Checkpoint)}
    if set(doc) != fields:
        raise CheckpointError(f"fields {sorted(doc)}, expected {sorted(fields)}")
    for k in ("model", "config_model", "fingerprint", "state", "counters"):
        if not isinstance(doc[k], dict):
            raise CheckpointError(f"{k} is a {type(doc[k]).__name__}, not an object")
    for k in ("model", "config_model", "fingerprint", "counters"):
        _plain_json(doc[k], k)
    for k, v in doc["counters"].items():
        if isinstance(v, bool) or not isinstance(v, int):
            raise CheckpointError(f"counter {k!r} = {v!r} is not an integer")
    saved = doc["saved_at"]
    if not is_real(saved):
        raise CheckpointError(f"saved_at = {saved!r} is not a time")
    if not isinstance(doc["version"], str):
        raise CheckpointError(f"version = {doc['version']!r} is not a string")
    _check_values(doc, "", False)
    return Checkpoint(model=doc["model"], config_model=doc["config_model"],
                      fingerprint=doc["fingerprint"], state=doc["state"],
                      counters=dict(doc["counters"]), saved_at=float(saved),
                      version=doc["version"])


def _encode(cp: Checkpoint) -> bytes:
    arrays: dict[str, np.ndarray] = {}
    doc = _flatten({"model": cp.model, "config_model": cp.config_model,
                    "fingerprint": cp.fingerprint, "state": cp.state,
                    "counters": cp.counters, "saved_at": cp.saved_at,
                    "version": cp.version}, arrays, "")
    meta = json.dumps(doc, sort_keys=True, allow_nan=True).encode()
    buf = io.BytesIO()
    # numpy's stub lets ** fill savez's allow_pickle: these keys are the state's names
    np.savez(buf, __meta__=np.frombuffer(meta, np.uint8), **arrays)  # type: ignore[arg-type]
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
        header = _json(raw[len(MAGIC):end], "checkpoint header")
    except CheckpointError as e:
        raise CheckpointError(f"{source}: {e}") from e
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
        try:
            arrays = _read_arrays(payload)
            meta = arrays.pop("__meta__")
        except (ValueError, KeyError, OSError, EOFError, zipfile.BadZipFile,
                zipfile.LargeZipFile, NotImplementedError, MemoryError,
                SyntaxError, tokenize.TokenError) as e:  # numpy parses .npy headers
            raise CheckpointError(f"payload unreadable: {e}") from e
        if meta.dtype != np.uint8 or meta.ndim != 1:
            raise CheckpointError("__meta__ is not a byte string")
        used: set[str] = set()
        doc = _unflatten(_json(meta.tobytes(), "the document"), arrays, used)
        if used != set(arrays):
            raise CheckpointError(f"arrays {sorted(set(arrays) - used)} not referenced")
        return _document(doc)
    except CheckpointError as e:
        raise CheckpointError(f"{source}: checkpoint {e}") from e


# ------------------------------------------------------------------ files
@contextmanager
def _directory(p: Path) -> Iterator[int]:
    """A descriptor of the directory of ``p`` (the directory may be reached through a
    link; the name in it never is)."""
    try:
        dfd = os.open(p.parent, os.O_RDONLY | _O_DIRECTORY | _O_CLOEXEC)
    except OSError as e:
        raise CheckpointPathError(f"{p}: the checkpoint's directory {p.parent} cannot be "
                                  f"opened: {e.strerror}") from e
    try:
        yield dfd
    finally:
        os.close(dfd)


def _kind(mode: int) -> str:
    return ("a symbolic link" if stat.S_ISLNK(mode) else "a directory" if stat.S_ISDIR(mode)
            else "a FIFO" if stat.S_ISFIFO(mode) else "a character device"
            if stat.S_ISCHR(mode) else "a block device" if stat.S_ISBLK(mode)
            else "a socket" if stat.S_ISSOCK(mode) else "not a regular file")


def _refuse(p: Path, mode: int) -> CheckpointPathError:
    return CheckpointPathError(f"{p}: the checkpoint path is {_kind(mode)}, not a regular "
                               f"file; it is left untouched")


def _lstat(dfd: int, name: str) -> os.stat_result | None:
    try:
        return os.stat(name, dir_fd=dfd, follow_symlinks=False)
    except FileNotFoundError:
        return None


def _read_regular(dfd: int, p: Path, max_bytes: int) -> tuple[bytes, os.stat_result]:
    """The bytes of the regular file ``p.name`` in ``dfd`` (never through a link, never
    blocking on a FIFO, at most ``max_bytes``), and its ``fstat``. A non-regular file
    is refused before it is opened (opening a device can act on it)."""
    before = _lstat(dfd, p.name)
    if before is None:
        raise FileNotFoundError(errno.ENOENT, "no checkpoint", str(p))
    if not stat.S_ISREG(before.st_mode):
        raise _refuse(p, before.st_mode)
    try:
        fd = os.open(p.name, os.O_RDONLY | _O_NOFOLLOW | _O_NONBLOCK | _O_CLOEXEC, dir_fd=dfd)
    except FileNotFoundError:
        raise
    except OSError as e:
        st = _lstat(dfd, p.name)
        if e.errno == errno.ELOOP or (st is not None and not stat.S_ISREG(st.st_mode)):
            raise _refuse(p, st.st_mode if st is not None else stat.S_IFLNK) from e
        raise CheckpointPathError(f"{p}: cannot open the checkpoint: {e.strerror}") from e
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise _refuse(p, st.st_mode)
        if st.st_size > max_bytes:
            raise CheckpointError(f"{p}: checkpoint is {st.st_size} bytes, more than the "
                                  f"{max_bytes} a checkpoint may have")
        chunks, left = [], st.st_size + 1  # one byte more: a file that grew is seen
        while left > 0:
            b = os.read(fd, min(left, 1 << 20))
            if not b:
                break
            chunks.append(b)
            left -= len(b)
    except OSError as e:
        raise CheckpointPathError(f"{p}: cannot read the checkpoint: {e.strerror}") from e
    finally:
        os.close(fd)
    raw = b"".join(chunks)
    if len(raw) != st.st_size:
        raise CheckpointError(f"{p}: checkpoint changed while it was read ({st.st_size} "
                              f"bytes stated, {len(raw)} read)")
    return raw, st


def _temp_name(name: str) -> str:
    return f".{name}.tmp.{os.getpid()}.{secrets.token_hex(4)}"


def _temp_pattern(name: str) -> re.Pattern[str]:
    # ours, and those of canrls before 0.2 (``.NAME.tmp.PID``)
    return re.compile(rf"\.{re.escape(name)}\.tmp\.\d+(\.[0-9a-f]{{8}})?\Z")


def _write_temp(dfd: int, name: str, data: bytes) -> str:
    """``data`` in a new private temporary beside ``name``, fsync-ed; returns its name."""
    for _ in range(16):
        tmp = _temp_name(name)
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | _O_NOFOLLOW | _O_CLOEXEC,
                         _MODE, dir_fd=dfd)
        except FileExistsError:  # anything there, a link too, is left alone
            continue
        break
    else:
        raise FileExistsError(errno.EEXIST, "no free temporary name", name)
    try:
        os.fchmod(fd, _MODE)  # whatever the umask
        view = memoryview(data)
        while view:
            n = os.write(fd, view)
            view = view[n:]
        os.fsync(fd)
    except BaseException:
        os.close(fd)
        os.unlink(tmp, dir_fd=dfd)
        raise
    os.close(fd)
    return tmp


def save_checkpoint(path: str | os.PathLike[str], cp: Checkpoint, *,
                    max_bytes: int = MAX_BYTES) -> int:
    """Write ``cp`` to ``path`` atomically (docs/daemon.md, "Checkpoints"); returns the
    bytes written.

    :raises CheckpointError: the state holds something a load would refuse (NaN, a
        type JSON lacks, more than ``max_bytes``): nothing is written.
    :raises CheckpointPathError: a link or another non-regular file is at ``path``, or
        its directory cannot be opened: nothing is written, nothing is replaced.
    :raises OSError: the file system refused.
    """
    p = Path(path)
    data = _encode(cp)
    if len(data) > max_bytes:
        raise CheckpointError(f"{p}: checkpoint would be {len(data)} bytes, more than the "
                              f"{max_bytes} a load accepts")
    _decode(data, str(p))  # never write what a load would refuse
    with _directory(p) as dfd:
        st = _lstat(dfd, p.name)
        if st is not None and not stat.S_ISREG(st.st_mode):
            raise _refuse(p, st.st_mode)
        tmp = _write_temp(dfd, p.name, data)
        try:
            os.rename(tmp, p.name, src_dir_fd=dfd, dst_dir_fd=dfd)
        except BaseException:
            os.unlink(tmp, dir_fd=dfd)
            raise
        os.fsync(dfd)  # make the rename itself durable
    return len(data)


def load_checkpoint(path: str | os.PathLike[str], *, max_bytes: int = MAX_BYTES) -> Checkpoint:
    """Read and verify a checkpoint (docs/daemon.md, "Checkpoints").

    :raises CheckpointPathError: the path is not a regular file (a link, a FIFO...).
    :raises CheckpointError: the file is not a valid checkpoint.
    :raises FileNotFoundError: there is none.
    """
    p = Path(path)
    with _directory(p) as dfd:
        raw, _ = _read_regular(dfd, p, max_bytes)
    return _decode(raw, str(p))


def set_aside(path: str | os.PathLike[str], st: os.stat_result | None = None) -> Path:
    """Rename a bad checkpoint to ``NAME.bad-YYYYmmdd-HHMMSS[-N]`` in its directory;
    returns the new path.

    Only a regular file is renamed (and, given ``st``, only the file it describes): a
    link or another non-regular file at ``path`` raises :class:`CheckpointPathError`.
    """
    p = Path(path)
    stamp = time.strftime("%Y%m%d-%H%M%S")
    with _directory(p) as dfd:
        now = _lstat(dfd, p.name)
        if now is None:
            raise FileNotFoundError(errno.ENOENT, "no checkpoint to set aside", str(p))
        if not stat.S_ISREG(now.st_mode):
            raise _refuse(p, now.st_mode)
        if st is not None and (now.st_dev, now.st_ino) != (st.st_dev, st.st_ino):
            raise CheckpointError(f"{p}: the checkpoint was replaced while it was checked")
        aside, k = f"{p.name}.bad-{stamp}", 1
        while _lstat(dfd, aside) is not None:
            aside, k = f"{p.name}.bad-{stamp}-{k}", k + 1
        os.rename(p.name, aside, src_dir_fd=dfd, dst_dir_fd=dfd)
        os.fsync(dfd)
    return p.with_name(aside)


def clean_temporaries(path: str | os.PathLike[str]) -> list[Path]:
    """Remove the temporaries a crashed save left beside ``path`` (regular files named
    ``.NAME.tmp.PID[.XXXXXXXX]`` only; nothing else is touched); returns them."""
    p = Path(path)
    pattern = _temp_pattern(p.name)
    removed = []
    with _directory(p) as dfd:
        for entry in os.scandir(dfd):
            if not pattern.match(entry.name):
                continue
            st = _lstat(dfd, entry.name)
            if st is None or not stat.S_ISREG(st.st_mode):
                continue
            os.unlink(entry.name, dir_fd=dfd)
            removed.append(p.with_name(entry.name))
    return removed


# ------------------------------------------------------------------ the daemon's use
def _what(x: Any) -> str:
    if isinstance(x, np.ndarray):
        return f"a {x.dtype} array of shape {x.shape}"
    return f"a {type(x).__name__}"


def _field(d: Mapping[str, Any], key: str, path: str, kind: type | tuple[type, ...]) -> Any:
    if key not in d:
        raise CheckpointError(f"{path}/{key} is missing")
    v = d[key]
    if not isinstance(v, kind) or isinstance(v, bool) and bool not in (
            kind if isinstance(kind, tuple) else (kind,)):
        raise CheckpointError(f"{path}/{key} is {_what(v)}")
    return v


def _array(d: Mapping[str, Any], key: str, path: str, shape: tuple[int, ...],
           kinds: str = "f") -> None:
    v = _field(d, key, path, np.ndarray)
    if v.dtype.kind not in kinds or v.shape != shape:
        raise CheckpointError(f"{path}/{key} is {_what(v)}, expected shape {shape}")


def _check_state(state: Mapping[str, Any], model: Model, written_by: Mapping[str, Any]) -> None:
    """The structure of :meth:`canrls.processor.SampleProcessor.state` for ``model``:
    types, the shapes of theta, P and the statistics, and the model that wrote it."""
    dt = state.get("dt")
    if dt is not None and not is_positive(dt):
        raise CheckpointError(f"state/dt = {dt!r} is not a period")
    window = _field(state, "window", "state", dict)
    lengths = set()
    for k, v in window.items():
        if not isinstance(v, np.ndarray) or v.dtype.kind != "f" or v.ndim != 1:
            raise CheckpointError(f"state/window/{k} is {_what(v)}")
        lengths.add(len(v))
    if len(lengths) > 1:
        raise CheckpointError(f"state/window: signals of {sorted(lengths)} samples")
    _field(state, "calibration", "state", (dict, type(None)))
    pipe = _field(state, "pipeline", "state", dict)
    if _field(pipe, "samples", "state/pipeline", int) < 0:
        raise CheckpointError("state/pipeline/samples is negative")
    written = _field(pipe, "model", "state/pipeline", dict)
    _plain_json(written, "state/pipeline/model")
    if written != written_by:
        raise CheckpointError("state/pipeline/model is not the checkpoint's model")
    ests = _field(pipe, "estimators", "state/pipeline", list)
    if len(ests) != len(model.equations):
        raise CheckpointError(f"state/pipeline/estimators: {len(ests)} for "
                              f"{len(model.equations)} equations")
    for i, (e, eq) in enumerate(zip(ests, model.equations, strict=True)):
        where, n = f"state/pipeline/estimators/{i}", eq.n
        if not isinstance(e, dict):
            raise CheckpointError(f"{where} is {_what(e)}")
        for k, kinds in (("rls", "f"), ("fixed", "iu")):
            sub = _field(e, k, where, dict)
            _array(sub, "theta", f"{where}/{k}", (n,), kinds)
            _array(sub, "P", f"{where}/{k}", (n, n), kinds)
        _array(e, "M", where, (n, n))
        _array(e, "v", where, (n,))


def _plain(d: Any) -> Any:
    """A JSON round trip: tuples become lists, as a checkpoint stores them."""
    return json.loads(json.dumps(d, allow_nan=True))


def fingerprint(settings: EstimatorSettings, dt: float | None) -> dict[str, Any]:
    """What besides the model must match for a checkpoint to resume: the stated sample
    period ``dt`` (None: measured from the frames; the state records the period it ran
    at, checked once it is measured) and every estimator setting (the forgetting factor
    too: ``set_lambda`` lives in the state)."""
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
    :param settings, dt: the estimator settings and the stated sample period, None when
        it is measured (:func:`fingerprint`).
    :param interval: seconds between periodic saves.
    :param max_parameters: most parameters of a model resumed from a checkpoint.
    :param max_bytes: largest checkpoint file.
    """

    def __init__(self, path: Path | None, config_model: Model, settings: EstimatorSettings,
                 dt: float | None, interval: float, *, max_parameters: int = MAX_PARAMETERS,
                 max_bytes: int = MAX_BYTES) -> None:
        self.path = path
        self.config_model = config_model
        self.fingerprint = fingerprint(settings, dt)
        self.interval = interval
        self.max_parameters = int(max_parameters)
        self.max_bytes = int(max_bytes)
        self.next_at = 0.0
        #: checkpoints written
        self.saved = 0
        #: why checkpoints are off for this run (None: they are on, or none configured)
        self.disabled: str | None = None
        #: held from :meth:`resume` until :meth:`close` (None: none taken)
        self.lock: CheckpointLock | None = None

    def close(self) -> None:
        """Release the checkpoint's lock (the daemon stopped)."""
        if self.lock is not None:
            self.lock.release()
            self.lock = None

    def _disable(self, why: CheckpointError) -> None:
        self.disabled = str(why)
        self.close()
        log.error("%s; running without checkpoints", why)

    def _prepare(self, path: Path) -> bool:
        """At start: stale temporaries removed, the location checked (a link or another
        non-regular file at the name, a directory that cannot be opened or written:
        checkpoints off). True when checkpoints can be used."""
        try:
            with _directory(path) as dfd:
                st = _lstat(dfd, path.name)
                if st is not None and not stat.S_ISREG(st.st_mode):
                    raise _refuse(path, st.st_mode)
                try:  # can the directory take our temporaries?
                    os.unlink(_write_temp(dfd, path.name, b""), dir_fd=dfd)
                except OSError as e:
                    raise CheckpointPathError(f"{path}: cannot write in the checkpoint's "
                                              f"directory: {e.strerror}") from e
            if self.lock is None:  # before anything is read or removed; may refuse
                self.lock = CheckpointLock(path)
            for t in clean_temporaries(path):
                log.warning("removed %s, the temporary of a save cut short", t)
        except CheckpointPathError as e:
            self._disable(e)
            return False
        except OSError as e:
            self._disable(CheckpointPathError(f"{path}: {e.strerror or e}"))
            return False
        return True

    def resume(self, restore: Callable[[Model, dict[str, Any]], T]
               ) -> tuple[T, Checkpoint] | None:
        """Load the checkpoint and rebuild from it: ``restore(model, state)``.

        None when there is none, when the location cannot be used (checkpoints are then
        off: :attr:`disabled`), or when it does not fit (another configured model, other
        settings, a model larger than :attr:`max_parameters`, a damaged file, a state
        ``restore`` refuses): such a file is set aside (:func:`set_aside`) and the
        estimator starts from the prior.
        """
        path = self.path
        if path is None or not self._prepare(path):
            return None
        st: os.stat_result | None = None
        try:
            try:
                with _directory(path) as dfd:
                    raw, st = _read_regular(dfd, path, self.max_bytes)
            except FileNotFoundError:
                log.info("no checkpoint at %s: starting from the prior", path)
                return None
            cp = _decode(raw, str(path))
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
            if len(model.parameters) > self.max_parameters:
                raise CheckpointError(f"{path}: checkpoint's model has {len(model.parameters)} "
                                      f"parameters, more than the {self.max_parameters} the "
                                      f"daemon publishes")
            try:
                _check_state(cp.state, model, cp.model)
            except CheckpointError as e:
                raise CheckpointError(f"{path}: checkpoint {e}") from e
            try:
                restored = restore(model, cp.state)
            except (CheckpointError, ConfigError):
                raise
            except Exception as e:  # a state the estimators cannot take: never fatal
                raise CheckpointError(f"{path}: checkpoint state does not fit the model "
                                      f"({type(e).__name__}: {e})") from e
        except CheckpointPathError as e:
            self._disable(e)
            return None
        except (CheckpointError, ConfigError) as e:
            try:
                where: Path | str = set_aside(path, st)
            except (OSError, CheckpointError) as e2:
                self._disable(CheckpointPathError(f"{path}: damaged checkpoint ({e}) cannot "
                                                  f"be set aside: {e2}"))
                return None
            log.error("checkpoint %s not loaded (%s); set aside as %s", path, e, where)
            return None
        log.info("resumed from checkpoint %s (%d samples, effects %s, saved %s)", path,
                 int(cp.state.get("pipeline", {}).get("samples", 0)),
                 ",".join(model.effect_names),
                 time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(cp.saved_at)))
        return restored, cp

    def due(self, now: float) -> bool:
        return now >= self.next_at

    def save(self, model: Model, state: dict[str, Any], counters: dict[str, int]) -> Path | None:
        """Write a checkpoint now (None: no checkpoint file configured, checkpoints off,
        or it could not be written: logged, the last good checkpoint stays, the daemon
        goes on)."""
        path = self.path
        if path is None or self.disabled is not None:
            return None
        cp = Checkpoint(model=_plain(model.to_dict()),
                        config_model=_plain(self.config_model.to_dict()),
                        fingerprint=self.fingerprint, state=state, counters=counters,
                        saved_at=time.time())
        try:
            save_checkpoint(path, cp, max_bytes=self.max_bytes)
        except (OSError, CheckpointError) as e:
            log.error("checkpoint %s: not written: %s", path, e)
            return None
        self.saved += 1
        log.debug("checkpoint written to %s", path)
        return path
