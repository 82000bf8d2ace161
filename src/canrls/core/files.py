"""Opening the files canrls reads and writes, one way for the CLI, the daemon and the
exporters.

Reading: only a regular file is read. A FIFO, device, socket or directory is refused
before it is opened (``stat``) and again after (``fstat`` of a descriptor opened with
``O_NONBLOCK``, so that a FIFO swapped in between cannot block), and a whole-file read
stops at a stated size. Logs are read in blocks; :class:`LineBound` bounds their lines.

Writing: never through a link (``O_NOFOLLOW``). A whole file (a log of ``canrls sim``,
a model, the C of ``export-c``, a report) goes to a fresh temporary beside its name,
created with ``O_EXCL``, and is renamed over the name when complete
(:func:`atomic_writer`), so a link planted at the name is replaced and one at a
temporary's name never touched; a stream (``--record``) is opened with
:func:`open_for_writing`.

Every error is raised as the ``error`` class the caller names (a
:class:`~canrls.core.errors.ConfigError` by default, a
:class:`~canrls.core.errors.LogFormatError` for logs), its message beginning with ``what``:
the option or key that named the file and the file (``"--dbc drive.dbc"``).
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import io
import os
import secrets
import shutil
import stat
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import BinaryIO

from canrls.core.errors import CanrlsError, ConfigError

__all__ = ["MAX_LINE", "MAX_CONFIG_BYTES", "MAX_DBC_BYTES", "MAX_MODEL_BYTES", "check_path",
           "kind", "open_regular", "read_bytes", "read_text", "LineBound", "atomic_writer",
           "check_writable", "open_for_writing", "temporary_name", "output_dir", "write_texts",
           "staged_dir", "ContentHash"]

#: Longest line of a log [bytes]: a CAN FD frame in any text format takes some 200.
MAX_LINE = 64 * 1024
#: Largest TOML configuration (canrls' own are a few kB).
MAX_CONFIG_BYTES = 4 * 1024 * 1024
#: Largest DBC (a whole vehicle's is a few MB).
MAX_DBC_BYTES = 64 * 1024 * 1024
#: Largest saved model (JSON; some 20 kB for 20 parameters).
MAX_MODEL_BYTES = 16 * 1024 * 1024

_O_CLOEXEC = getattr(os, "O_CLOEXEC", 0)
_O_NOFOLLOW = getattr(os, "O_NOFOLLOW", 0)
_O_NONBLOCK = getattr(os, "O_NONBLOCK", 0)
_O_NOCTTY = getattr(os, "O_NOCTTY", 0)

ErrorType = type[CanrlsError]


def kind(mode: int) -> str:
    """What a file of this ``st_mode`` is, in words (``"a FIFO"``)."""
    for test, name in ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO"),
                       (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISSOCK, "a socket"), (stat.S_ISLNK, "a symbolic link"),
                       (stat.S_ISREG, "a regular file")):
        if test(mode):
            return name
    return "not a regular file"


def check_path(path: str | os.PathLike[str], what: str, error: ErrorType = ConfigError
               ) -> Path:
    """``path`` as a :class:`Path`, refused when it is empty or holds a NUL byte (which no
    file name can)."""
    text = os.fspath(path)
    if isinstance(text, bytes) or not text or "\0" in text:
        why = " (it holds a NUL byte)" if text and "\0" in str(text) else ""
        raise error(f"{what}: {text!r} is not a file name{why}")
    return Path(text)


def _oserror(e: OSError) -> str:
    return e.strerror or str(e)


def open_regular(path: str | os.PathLike[str], what: str, error: ErrorType = ConfigError
                 ) -> io.FileIO:
    """An unbuffered binary file object of the regular file at ``path`` (links followed),
    refused without reading when it is anything else; see the module docstring."""
    p = check_path(path, what, error)
    try:
        st = os.stat(p)
    except OSError as e:
        raise error(f"{what}: cannot read: {_oserror(e)}") from e
    if not stat.S_ISREG(st.st_mode):
        raise error(f"{what}: is {kind(st.st_mode)}, not a regular file")
    try:
        fd = os.open(p, os.O_RDONLY | _O_NONBLOCK | _O_NOCTTY | _O_CLOEXEC)
    except OSError as e:
        raise error(f"{what}: cannot read: {_oserror(e)}") from e
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):  # swapped since the stat above
            raise error(f"{what}: is {kind(st.st_mode)}, not a regular file")
        if _O_NONBLOCK:
            os.set_blocking(fd, True)
        return os.fdopen(fd, "rb", buffering=0)
    except BaseException:
        os.close(fd)
        raise


class ContentHash:
    """The SHA-256 of a file's bytes, fed by a reader as it reads the file from its start
    (:func:`canrls.can.logs.read_frames` ``digest=``), so that the file is read once for
    its frames and its hash; :meth:`finish` hashes what the reader left unread."""

    def __init__(self) -> None:
        self._h = hashlib.sha256()
        #: bytes hashed so far, from the file's start
        self.offset = 0
        self.complete = False

    def update(self, data: bytes | memoryview) -> None:
        """The next bytes of the file, in order."""
        self._h.update(data)
        self.offset += len(data)

    def finish(self, fd: int) -> None:
        """Hash the file open at ``fd`` from :attr:`offset` to its end (``pread``: the
        descriptor's position is left alone)."""
        while chunk := os.pread(fd, 1 << 20, self.offset):
            self.update(chunk)
        self.complete = True

    def hexdigest(self) -> str:
        """The hash (hex, 64 characters) of the whole file.

        :raises RuntimeError: the file was not read to its end (:meth:`finish`).
        """
        if not self.complete:
            raise RuntimeError("ContentHash: the file was not read to its end")
        return self._h.hexdigest()


def read_bytes(path: str | os.PathLike[str], what: str, *, limit: int,
               error: ErrorType = ConfigError) -> bytes:
    """The whole regular file at ``path``, refused when it holds more than ``limit``
    bytes (checked before reading, and while reading: it may grow)."""
    with open_regular(path, what, error) as f:
        size = os.fstat(f.fileno()).st_size
        if size > limit:
            raise error(f"{what}: {size} bytes, more than the {limit} a file of this "
                        f"kind may have")
        try:
            data = f.read(limit + 1)
        except OSError as e:
            raise error(f"{what}: cannot read: {_oserror(e)}") from e
    if len(data) > limit:
        raise error(f"{what}: more than the {limit} bytes a file of this kind may have")
    return data


def read_text(path: str | os.PathLike[str], what: str, *, limit: int,
              error: ErrorType = ConfigError) -> str:
    """The regular file at ``path`` as UTF-8 text, at most ``limit`` bytes."""
    data = read_bytes(path, what, limit=limit, error=error)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as e:
        line = data.count(b"\n", 0, e.start) + 1
        raise error(f"{what}: line {line}: not UTF-8 text (byte 0x{data[e.start]:02x})"
                    ) from e


class LineBound(io.RawIOBase):
    """A binary stream that passes ``raw`` through and raises ``error`` (naming ``what``
    and the line) as soon as a line runs longer than ``max_line`` bytes: the readers
    above it (:class:`io.TextIOWrapper`, python-can's) then never buffer more.

    ``\\n`` and ``\\r`` both end a line (as universal newlines do). Each read takes at
    most ``max_line`` bytes, so a run inside one read is shorter than the bound and only
    the runs that cross reads need counting."""

    def __init__(self, raw: io.RawIOBase, what: str, *, max_line: int = MAX_LINE,
                 error: ErrorType = ConfigError) -> None:
        super().__init__()
        self.raw = raw
        self.what = what
        self.max_line = max_line
        self.error = error
        self.run = 0      # bytes since the last line end
        self.lines = 0    # line ends passed

    def readable(self) -> bool:
        return True

    # narrower than RawIOBase's buffer: the buffered readers above hand it these
    def readinto(self, b: bytearray | memoryview) -> int:  # type: ignore[override]
        view = memoryview(b).cast("B")[:self.max_line]
        n = self.raw.readinto(view) or 0
        if n == 0:
            return 0
        chunk = bytes(view[:n])
        first = min((i for i in (chunk.find(b"\n"), chunk.find(b"\r")) if i >= 0),
                    default=-1)
        if first < 0:
            self.run += n
        else:
            if self.run + first > self.max_line:
                self._too_long()
            self.run = n - 1 - max(chunk.rfind(b"\n"), chunk.rfind(b"\r"))
        if self.run > self.max_line:
            self.lines += chunk.count(b"\n")
            self._too_long()
        self.lines += chunk.count(b"\n")
        return n

    def _too_long(self) -> None:
        raise self.error(f"{self.what}: line {self.lines + 1} is longer than "
                         f"{self.max_line} bytes: not a line of a CAN log")

    def tell(self) -> int:
        return self.raw.tell()

    def close(self) -> None:
        try:
            self.raw.close()
        finally:
            super().close()


def temporary_name(path: Path) -> Path:
    """A fresh temporary name beside ``path``: ``NAME.XXXXXXXX.part``."""
    return path.with_name(f"{path.name}.{secrets.token_hex(4)}.part")


@contextlib.contextmanager
def atomic_writer(path: str | os.PathLike[str], what: str, error: ErrorType = ConfigError,
                  *, replace: bool = True) -> Iterator[BinaryIO]:
    """Write a whole file: yields a binary file object on a fresh temporary beside
    ``path`` (``O_EXCL | O_NOFOLLOW``, mode 0666 less the umask), renamed over ``path``
    when the block ends without an exception, removed otherwise (also on
    ``KeyboardInterrupt`` and ``SystemExit``).

    A link at ``path`` is replaced, never written through; a directory or other
    non-regular file at ``path`` is refused before anything is written, and so is an
    existing file when ``replace`` is False."""
    p = check_path(path, what, error)
    _check_target(p, what, error, replace)
    fd = -1
    for _ in range(8):
        tmp = temporary_name(p)
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | _O_NOFOLLOW
                         | _O_CLOEXEC, 0o666)
            break
        except FileExistsError:
            continue
        except OSError as e:
            raise error(f"{what}: cannot write: {_oserror(e)}") from e
    if fd < 0:
        raise error(f"{what}: cannot write: no free temporary name beside it")
    keep = -1
    try:
        keep = os.dup(fd)  # to sync the file even when the caller's writer closed it
        with os.fdopen(fd, "wb") as f:
            yield f
        os.fsync(keep)
        _check_target(p, what, error, replace)
        os.rename(tmp, p)
    except OSError as e:
        _unlink(tmp)
        raise error(f"{what}: cannot write: {_oserror(e)}") from e
    except BaseException:
        _unlink(tmp)
        raise
    finally:
        if keep >= 0:
            os.close(keep)


def _check_target(p: Path, what: str, error: ErrorType, replace: bool,
                  links: bool = True) -> None:
    try:
        st = os.lstat(p)
    except FileNotFoundError:
        return
    except OSError as e:
        raise error(f"{what}: cannot write: {_oserror(e)}") from e
    if stat.S_ISLNK(st.st_mode) and replace and links:
        return  # the rename replaces the link itself
    if not stat.S_ISREG(st.st_mode):
        raise error(f"{what}: is {kind(st.st_mode)}, not a file canrls may write")
    if not replace:
        raise error(f"{what}: exists already (canrls does not overwrite it)")


def check_writable(path: str | os.PathLike[str], what: str, error: ErrorType = ConfigError,
                   *, replace: bool = True, links: bool = True) -> Path:
    """Whether canrls could write a file at ``path``, checked before any work: its
    directory exists, and nothing but a regular file (or, with ``links``, a link that
    :func:`atomic_writer` replaces) is at the name; with ``replace`` False, nothing at
    all. Returns the path."""
    p = check_path(path, what, error)
    parent = p.parent
    try:
        st = os.stat(parent)
    except OSError as e:
        raise error(f"{what}: cannot write into {parent}: {_oserror(e)}") from e
    if not stat.S_ISDIR(st.st_mode):
        raise error(f"{what}: {parent} is {kind(st.st_mode)}, not a directory")
    _check_target(p, what, error, replace, links)
    return p


def output_dir(path: str | os.PathLike[str], what: str, error: ErrorType = ConfigError
               ) -> Path:
    """``path`` made a directory (with its parents), refused when something else is
    there; a link to a directory is the user's choice, followed."""
    out = check_path(path, what, error)
    try:
        st = os.stat(out)
    except FileNotFoundError:
        try:
            out.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise error(f"{what}: cannot make the directory: {_oserror(e)}") from e
        return out
    except OSError as e:
        raise error(f"{what}: {_oserror(e)}") from e
    if not stat.S_ISDIR(st.st_mode):
        raise error(f"{what}: exists and is {kind(st.st_mode)}, not a directory")
    return out


def write_texts(path: str | os.PathLike[str], texts: Iterable[tuple[str, str]], what: str,
                error: ErrorType = ConfigError) -> list[Path]:
    """Each ``(name, text)`` written as UTF-8 to ``name`` in the directory ``path``
    (:func:`output_dir`), through :func:`atomic_writer`: a link planted at a name is
    replaced, never written through. Returns the paths."""
    out = output_dir(path, what, error)
    files: list[Path] = []
    for name, text in texts:
        p = out / name
        with atomic_writer(p, f"{what}: {name}", error) as f:
            f.write(text.encode("utf-8"))
        files.append(p)
    return files


@contextlib.contextmanager
def staged_dir(path: str | os.PathLike[str], what: str, error: ErrorType = ConfigError,
               *, last: str | None = None) -> Iterator[Path]:
    """Write a directory's files as a whole: yields a fresh temporary directory
    (``.NAME.XXXXXXXX.part``) inside ``path`` if it is a directory, else beside it (on
    the file system of ``path`` either way, so its files can be renamed); when the block
    ends without an exception, each file in it is renamed into ``path``
    (:func:`output_dir`: made if missing), ``last`` after the others (a page after its
    figures). On an exception (``KeyboardInterrupt`` too) ``path`` is left as it was.
    The temporary is removed either way."""
    final = check_path(path, what, error)
    where = final if final.is_dir() else final.parent  # a link to a directory: followed
    try:
        where.mkdir(parents=True, exist_ok=True)
        stage = Path(tempfile.mkdtemp(prefix=f".{final.name}.", suffix=".part", dir=where))
    except OSError as e:
        raise error(f"{what}: cannot create the directory: {_oserror(e)}") from e
    try:
        yield stage
        out = output_dir(final, what, error)
        for name in sorted(os.listdir(stage), key=lambda n: n == last):
            _check_target(out / name, f"{what}: {name}", error, True)
            try:  # a link at the name is replaced, never written through
                os.replace(stage / name, out / name)
            except OSError as e:
                raise error(f"{what}: {name}: cannot write: {_oserror(e)}") from e
    finally:
        shutil.rmtree(stage, ignore_errors=True)


def _unlink(p: Path) -> None:
    with contextlib.suppress(OSError):
        os.unlink(p)


def open_for_writing(path: str | os.PathLike[str], what: str,
                     error: ErrorType = ConfigError) -> BinaryIO:
    """A buffered binary file object writing the regular file at ``path`` from its start
    (created, or truncated), never through a link (``O_NOFOLLOW``): for streams such as
    the daemon's recording. Anything else at ``path`` (a link, FIFO, device, socket,
    directory) is refused without writing."""
    p = check_path(path, what, error)
    try:
        st = os.lstat(p)
    except FileNotFoundError:
        pass
    except OSError as e:
        raise error(f"{what}: cannot write: {_oserror(e)}") from e
    else:
        if not stat.S_ISREG(st.st_mode):
            raise error(f"{what}: is {kind(st.st_mode)}, not a file canrls may write")
    try:
        # O_NONBLOCK: a FIFO swapped in cannot block the open (ENXIO without a reader)
        fd = os.open(p, os.O_WRONLY | os.O_CREAT | _O_NOFOLLOW | _O_NONBLOCK | _O_NOCTTY
                     | _O_CLOEXEC, 0o666)
    except OSError as e:
        if e.errno == errno.ELOOP:
            raise error(f"{what}: is a symbolic link, not a file canrls may write") from e
        raise error(f"{what}: cannot write: {_oserror(e)}") from e
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise error(f"{what}: is {kind(st.st_mode)}, not a file canrls may write")
        os.ftruncate(fd, 0)
        if _O_NONBLOCK:
            os.set_blocking(fd, True)
        return os.fdopen(fd, "wb")
    except OSError as e:
        os.close(fd)
        raise error(f"{what}: cannot write: {_oserror(e)}") from e
    except BaseException:
        os.close(fd)
        raise
