"""Reading and writing CAN logs as streams of :class:`~canrls.can.frameblock.FrameBlock`.

Formats
-------
``.log``
    candump (``(1700000000.123456) can0 101#0011223344556677``). Parsed by canrls's
    own reader, because the offline replay must reach millions of frames per second:
    the file is read into one reusable buffer and a compiled pass
    (:mod:`canrls.can.candump`) turns the bytes into frame arrays; lines of any other
    layout (remote frames ``R``, CAN FD ``##``, odd spacing, comments) take a per-line
    path that follows python-can's ``CanutilsLogReader``, and keep their place in the
    file. Both paths give the same frames, timestamps bit for bit
    (``float("1700000000.123456")``). Writing is compiled too, and writes exactly what
    ``f"({t:f}) {channel} {id}#{data}"`` would.
``.asc``, ``.blf``, ``.trc``, ``.csv`` (and anything else ``can.LogReader`` knows)
    read through python-can's readers, packed into blocks.

Reading streams in blocks of ``chunk_size`` frames, so memory stays flat in the
log's length. A line that cannot be parsed is a :class:`~canrls.core.errors.LogFormatError`
naming the file and line number, unless ``skip_bad_lines=True`` (the named
opt-out), in which case it is counted in :attr:`LogReadStats.bad_lines`. A timestamp
that is not a time (:func:`canrls.core.checks.is_time`: not finite or beyond
:data:`~canrls.core.checks.MAX_TIMESTAMP`, ``(inf)``, ``(1e300)``) makes its line bad: it
is no time of a frame, and read as one it would put every later frame out of time. The
live path judges its frames by the same rule (:mod:`canrls.processor.times`).
"""

from __future__ import annotations

import dataclasses
import io
import itertools
import locale
import os
from collections.abc import Callable, Generator, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import can
import numpy as np
import numpy.typing as npt

from canrls.can import candump
from canrls.can.frameblock import MAX_DATA_LENGTH, FrameBlock
from canrls.can.writers import writer_on
from canrls.core.background import Background
from canrls.core.checks import MAX_TIMESTAMP, describe_time, is_time
from canrls.core.errors import ConfigError, LogFormatError
from canrls.core.files import (
    MAX_LINE,
    ContentHash,
    LineBound,
    atomic_writer,
    check_path,
    open_regular,
)

__all__ = ["LogReadStats", "read_frames", "write_candump", "write_log", "check_channel",
           "empty_log_error", "CAN_ERR_FLAG", "MAX_CHANNEL"]

#: Linux SocketCAN error-frame flag in the 32-bit CAN ID (candump writes it in the ID).
CAN_ERR_FLAG = candump.CAN_ERR_FLAG
_EFF_MASK = candump.EFF_MASK
#: Longest channel name written into a log (Linux interface names have at most 15).
MAX_CHANNEL = 64

#: Blocks of at least this many frames are read ahead in a thread (smaller ones cost
#: more in thread hand-overs than the overlap saves).
READ_AHEAD = 4096

_T = TypeVar("_T")
_G = TypeVar("_G", bound=np.generic)


@dataclass
class LogReadStats:
    """What a read went through: frames, lines and bytes seen."""

    frames: int = 0
    lines: int = 0
    bad_lines: int = 0
    #: candump lines the compiled parser handed back to the per-line Python path
    slow_lines: int = 0
    bytes_read: int = 0
    total_bytes: int = 0


def empty_log_error(path: str | os.PathLike[str], bad_lines: int = 0) -> LogFormatError:
    """The error of a log without a CAN frame (``canrls fit`` and ``export-c --vectors``
    alike), with the unparsable lines skipped, if any."""
    return LogFormatError(f"{path}: no CAN frames in the log"
                          + (f" ({bad_lines} unparsable lines skipped)" if bad_lines else ""))


def read_frames(
    path: str | os.PathLike[str],
    chunk_size: int = 65536,
    *,
    skip_bad_lines: bool = False,
    stats: LogReadStats | None = None,
    progress: Callable[[int, int], None] | None = None,
    digest: ContentHash | None = None,
) -> Iterator[FrameBlock]:
    """Yield the frames of a log file in blocks of at most about ``chunk_size`` frames.

    Parameters
    ----------
    path : log file (``.log`` candump, ``.asc``, ``.blf``, ``.trc``, ``.csv``, ...)
    chunk_size : frames per block (memory stays proportional to it)
    skip_bad_lines : count unparsable candump lines instead of raising
    stats : filled in while reading
    progress : called as ``progress(bytes_done, bytes_total)`` after each block
    digest : fed the file's bytes as they are read (a candump log is read once for both;
        other formats are hashed after their frames), complete after the last block
    """
    p = check_path(path, "log file", LogFormatError)
    if not p.exists():
        raise LogFormatError(f"{p}: no such log file")
    st = stats if stats is not None else LogReadStats()
    # a regular file only: a FIFO, device or directory is refused before it is opened
    with open_regular(p, str(p), LogFormatError) as f:
        st.total_bytes = os.fstat(f.fileno()).st_size
        # python-can's readers close the file they read: the digest reads its own copy
        fd = os.dup(f.fileno()) if digest is not None else -1
        try:
            if p.suffix.lower() == ".log":
                src = f if digest is None else _Hashed(f, digest)
                yield from _read_candump(src, p, chunk_size, skip_bad_lines, st, progress)
            else:
                yield from _read_python_can(f, p, chunk_size, st, progress)
            if digest is not None:
                digest.finish(fd)
        finally:
            if fd >= 0:
                os.close(fd)


class _Hashed:
    """A file read with ``readinto`` from its start, each byte read fed to ``digest``."""

    def __init__(self, f: io.FileIO, digest: ContentHash) -> None:
        self.f = f
        self.digest = digest

    def readinto(self, b: memoryview) -> int:
        n = self.f.readinto(b) or 0
        if n:
            self.digest.update(b[:n])
        return n


# --------------------------------------------------------------------------- candump


def _read_candump(f: io.FileIO | _Hashed, path: Path, chunk_size: int, skip_bad: bool,
                  st: LogReadStats, progress: Callable[[int, int], None] | None
                  ) -> Iterator[FrameBlock]:
    """Blocks of at most ``chunk_size`` frames (:func:`_parse_candump`); from
    :data:`READ_AHEAD` frames a block, the next block is read and parsed in a thread while
    the caller works on the current one (the file read and the C parser release the GIL).
    ``st`` counts what the caller was given."""
    own = LogReadStats(total_bytes=st.total_bytes)  # the parser's, a block ahead
    steps = _parse_candump(f, path, chunk_size, skip_bad, own)
    # the first block is the caller's to wait for; a log it holds whole (a short log)
    # leaves nothing to read ahead, so no thread is started for it
    first = next(steps, None)
    if first is None:
        return
    whole = first[1].bytes_read >= st.total_bytes
    rest = steps if whole or chunk_size < READ_AHEAD else _read_ahead(steps)
    for block, seen in itertools.chain((first,), rest):
        for name in ("frames", "lines", "bad_lines", "slow_lines", "bytes_read"):
            setattr(st, name, getattr(seen, name))
        if len(block):
            yield block
        if progress is not None:
            progress(st.bytes_read, st.total_bytes)


_END = object()


def _read_ahead(it: Generator[_T, None, None]) -> Iterator[_T]:
    """The items of ``it``, each next one made in a thread while the caller works on the
    current one (a thread per item: a generator left suspended holds none); ``it`` is
    closed at the end, or when the caller stops."""
    ahead: Background[Any] = Background(next, it, _END, name="canrls log reader")
    try:
        while True:
            item = ahead.result()
            if item is _END:
                return
            ahead = Background(next, it, _END, name="canrls log reader")
            yield item
    finally:
        ahead.join()  # an item made for a caller that stopped early is dropped
        it.close()


def _parse_candump(f: io.FileIO | _Hashed, path: Path, chunk_size: int, skip_bad: bool,
                   st: LogReadStats) -> Generator[tuple[FrameBlock, LogReadStats], None, None]:
    """Each parse step's block (possibly empty) and a copy of ``st`` after it, reading
    ``f`` into one reusable buffer.

    The compiled parser (:func:`canrls.can.candump.parse`) takes every line of the common
    layout; the others come back as "slow" lines with the row they precede, go through
    :func:`_parse_candump_line` and are inserted there, so the file's order is kept. A
    line longer than :data:`~canrls.core.files.MAX_LINE` is a bad line: the buffer never
    grows for it (skipped with ``skip_bad``, unread beyond the bound).
    """
    cap = max(1, int(chunk_size))
    # ~40 bytes per line in a typical classic-CAN candump file; a bit more so that one
    # buffer usually fills a whole block. Unparsed bytes are buf[start:fill].
    buf = np.empty(max(1 << 16, cap * 48), np.uint8)
    start = fill = 0
    eof = False
    need = True  # read before parsing (the buffer holds no complete line)
    line_no = 0
    slow = np.empty((cap, 4), np.int64)
    #: inside a line too long to keep ("comment" or "bad"), dropping it up to its end
    skipping: str | None = None
    while True:
        if not eof and (need or fill - start < len(buf) // 2):
            if start:
                buf[:fill - start] = buf[start:fill]
                fill -= start
                start = 0
            if fill == len(buf):  # one line fills the buffer: longer than MAX_LINE
                comment = bytes(buf[:256]).lstrip().startswith(b"#")
                if not (comment or skip_bad):
                    raise LogFormatError(f"{path}:{line_no + 1}: line longer than "
                                         f"{MAX_LINE} bytes: not a candump line")
                skipping, fill = "comment" if comment else "bad", 0
                st.bytes_read += len(buf)
            got = f.readinto(buf.data[fill:])
            if got:
                fill += got
            else:
                eof = True
            need = False
        if skipping:
            ends = np.flatnonzero(buf[:fill] == 10)
            if len(ends) == 0 and not eof:
                st.bytes_read += fill
                fill, need = 0, True
                continue
            st.bad_lines += skipping == "bad"
            line_no += 1
            st.lines += 1
            cut = int(ends[0]) + 1 if len(ends) else fill
            st.bytes_read += cut
            buf[:fill - cut] = buf[cut:fill]
            fill -= cut
            skipping = None
        view = buf[start:fill]
        b = FrameBlock(np.empty(cap, np.float64), np.empty(cap, np.uint32),
                       np.empty(cap, np.bool_), np.zeros(cap, np.bool_),
                       np.empty(cap, np.bool_), np.empty(cap, np.uint8),
                       np.empty((cap, 8), np.uint8))
        used, rows, nslow, nlines = candump.parse(
            view, len(view), eof, b.t, b.arbitration_id, b.is_extended, b.is_error,
            b.dlc, b.data, slow)
        if used == 0:
            if eof:
                break
            need = True
            continue
        block = b if rows == cap else b.take(slice(0, rows))
        if nslow:
            st.slow_lines += nslow
            block = _with_slow_lines(block, view, slow[:nslow], path, line_no, skip_bad,
                                     st)
        line_no += nlines
        st.lines += nlines
        st.bytes_read += used
        start += used
        st.frames += len(block)
        yield block, dataclasses.replace(st)


def _with_slow_lines(block: FrameBlock, buf: npt.NDArray[np.uint8],
                     slow: npt.NDArray[np.int64], path: Path, line0: int, skip_bad: bool,
                     st: LogReadStats) -> FrameBlock:
    """Parse the lines the compiled parser left (per line, as python-can) and insert them."""
    msgs: list[can.Message] = []
    before: list[int] = []
    for row, a, e, k in slow.tolist():
        text = buf[a:min(e, a + MAX_LINE + 1)].tobytes().decode("ascii", errors="replace")
        if not text.strip() or text.lstrip().startswith("#"):
            continue
        try:
            if e - a > MAX_LINE:
                raise ValueError(f"{e - a} bytes long, a line has at most {MAX_LINE}")
            msgs.append(_parse_candump_line(text))
            before.append(row)
        except ValueError as err:
            if skip_bad:
                st.bad_lines += 1
                continue
            raise LogFormatError(
                f"{path}:{line0 + k + 1}: not a candump line ({err}): {text[:80]!r}") from err
    if not msgs:
        return block
    extra = FrameBlock.from_messages(msgs)
    pos = np.asarray(before, np.intp)
    width = max(block.data.shape[1], extra.data.shape[1])

    def pad(d: npt.NDArray[np.uint8]) -> npt.NDArray[np.uint8]:
        return d if d.shape[1] == width else np.pad(d, ((0, 0), (0, width - d.shape[1])))

    def merged(a: npt.NDArray[_G], b: npt.NDArray[_G]) -> npt.NDArray[_G]:
        return np.insert(a, pos, b, axis=0)

    return FrameBlock(merged(block.t, extra.t),
                      merged(block.arbitration_id, extra.arbitration_id),
                      merged(block.is_extended, extra.is_extended),
                      merged(block.is_remote, extra.is_remote),
                      merged(block.is_error, extra.is_error),
                      merged(block.dlc, extra.dlc),
                      merged(pad(block.data), pad(extra.data)))


def _parse_candump_line(text: str) -> can.Message:
    """One candump line, the way python-can's CanutilsLogReader reads it."""
    parts = text.split()
    if len(parts) < 3 or not (parts[0].startswith("(") and parts[0].endswith(")")):
        raise ValueError("expected '(timestamp) channel frame'")
    timestamp = float(parts[0][1:-1])
    if not is_time(timestamp):  # inf, nan, 1e300: no time of a frame
        raise ValueError(describe_time(timestamp))
    channel = parts[1]
    frame = parts[2]
    if "#" not in frame:
        raise ValueError("frame has no '#'")
    can_id_s, rest = frame.split("#", 1)
    if len(can_id_s) > 8:  # masked to 29 bits, "1000000101" would read as 0x101
        raise ValueError(f"the ID {can_id_s[:20]!r} has {len(can_id_s)} hex digits: not a "
                         f"CAN ID (at most 8 digits, 29 bits and candump's flags)")
    can_id = int(can_id_s, 16)
    is_fd = rest.startswith("#")
    is_remote = False
    data = b""
    if is_fd:
        data = bytes.fromhex(rest[2:])  # rest[1] holds the FD flags
    elif rest.startswith("R"):
        is_remote = True
    else:
        data = bytes.fromhex(rest)
    if len(data) > MAX_DATA_LENGTH:
        raise ValueError(f"{len(data)} data bytes, a CAN frame carries at most "
                         f"{MAX_DATA_LENGTH}")
    is_error = len(can_id_s) > 3 and bool(can_id & CAN_ERR_FLAG)
    return can.Message(timestamp=timestamp, channel=channel,
                       arbitration_id=can_id & _EFF_MASK,
                       is_extended_id=len(can_id_s) > 3 and not is_error,
                       is_remote_frame=is_remote, is_error_frame=is_error,
                       is_fd=is_fd, dlc=len(data), data=data)


# --------------------------------------------------------------------------- python-can readers


def _python_can_reader(f: io.FileIO, path: Path) -> can.io.generic.MessageReader:
    """python-can's reader for the suffix of ``path``, reading ``f``: a text format
    through :class:`~canrls.core.files.LineBound` (no line longer than
    :data:`~canrls.core.files.MAX_LINE` is buffered), a binary one straight."""
    from can.io.generic import BinaryIOMessageReader, TextIOMessageReader
    from can.io.player import MESSAGE_READERS

    suffix = path.suffix.lower()
    cls = MESSAGE_READERS.get(suffix)
    try:
        if cls is not None and issubclass(cls, TextIOMessageReader):
            raw = io.BufferedReader(LineBound(f, str(path), error=LogFormatError))
            text = io.TextIOWrapper(raw, encoding=locale.getpreferredencoding(False))
            return cls(file=text)
        if cls is not None and issubclass(cls, BinaryIOMessageReader):
            return cls(file=io.BufferedReader(f))
        # formats python-can opens by name (.db, .mf4, compressed): the file was checked
        return can.LogReader(str(path))
    except LogFormatError:
        raise
    except Exception as e:  # python-can readers raise many kinds on bad input
        raise LogFormatError(f"{path}: cannot read this log format ({e})") from e


def _read_python_can(f: io.FileIO, path: Path, chunk_size: int, st: LogReadStats,
                     progress: Callable[[int, int], None] | None) -> Iterator[FrameBlock]:
    reader = _python_can_reader(f, path)
    buf: list[can.Message] = []

    def position() -> int:
        """Bytes read so far, where the reader's file tells (binary formats may not)."""
        try:
            return min(int(f.tell()), st.total_bytes)
        except (AttributeError, OSError, ValueError):
            return 0

    def block(msgs: list[can.Message]) -> FrameBlock:
        try:
            return FrameBlock.from_messages(msgs)
        except (ValueError, OverflowError) as e:
            raise LogFormatError(f"{path}: frames {st.frames + 1}..{st.frames + len(msgs)}: "
                                 f"{e}") from e

    with reader:
        it = iter(reader)
        while True:
            try:
                msg = next(it)
            except StopIteration:
                break
            except LogFormatError:
                raise
            except Exception as e:  # python-can readers raise many kinds on bad input
                raise LogFormatError(
                    f"{path}: unreadable after frame {st.frames + len(buf)} ({e})") from e
            k = st.frames + len(buf) + 1
            if not is_time(msg.timestamp):
                raise LogFormatError(
                    f"{path}: frame {k} has the timestamp {msg.timestamp!r}, not a time "
                    f"(finite, at most {MAX_TIMESTAMP:g} s)")
            if not 0 <= msg.arbitration_id <= _EFF_MASK:
                raise LogFormatError(
                    f"{path}: frame {k} has the ID 0x{msg.arbitration_id:X}, not a CAN ID "
                    f"(at most 29 bits, 0x{_EFF_MASK:X})")
            buf.append(msg)
            if len(buf) >= chunk_size:
                out = block(buf)
                st.frames += len(buf)
                yield out
                buf = []
                if progress is not None:
                    progress(position(), st.total_bytes)
    if buf:
        out = block(buf)
        st.frames += len(buf)
        yield out
    st.bytes_read = st.total_bytes
    if progress is not None:
        progress(st.total_bytes, st.total_bytes)


# --------------------------------------------------------------------------- writing


def _candump_lines(block: FrameBlock, channel: str) -> str:
    """Per-row formatting (the reference for :func:`_candump_bytes`, and its fallback)."""
    out = []
    for k in range(len(block)):
        cid = int(block.arbitration_id[k])
        if block.is_error[k]:
            ids = f"{cid | CAN_ERR_FLAG:08X}"
        elif block.is_extended[k]:
            ids = f"{cid:08X}"
        else:
            ids = f"{cid:03X}"
        dlc = int(block.dlc[k])
        if block.is_remote[k]:
            body = "R"
        elif dlc > 8:
            body = "#0" + block.data[k, :dlc].tobytes().hex().upper()
        else:
            body = block.data[k, :dlc].tobytes().hex().upper()
        out.append(f"({block.t[k]:f}) {channel} {ids}#{body}\n")
    return "".join(out)


def _split_timestamps(t: npt.NDArray[np.float64]
                      ) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]] | None:
    """Exact ``(seconds, microseconds)`` of ``f"{t:f}"`` per row, or None (use the fallback).

    The whole seconds are split off first (``t - floor(t)`` is exact), so that the
    microseconds ``rint(frac * 1e6)`` are correctly rounded unless ``frac * 1e6`` lies
    within a few ulps of a half-integer (its own rounding error could then flip the
    tie); those rows take Python's formatting, which rounds the exact binary value.
    Without the split, an epoch time (``candump -l``: 1.7e9 s, 1.7e15 us, ulp 0.25 us)
    put every row within those ulps and formatted every row in Python.
    """
    t = np.ascontiguousarray(t, np.float64)
    with np.errstate(invalid="ignore", over="ignore"):
        ok = (t >= 0.0) & (t * 1e6 < 2.0 ** 52)
        whole = np.floor(t)
        x = (t - whole) * 1e6
        fr = x - np.floor(x)
        near = np.abs(fr - 0.5) <= 8.0 * np.spacing(x)
    if not ok.all():
        return None
    sec = whole.astype(np.int64)
    us = np.rint(x).astype(np.int64)
    carry = us >= 1_000_000
    sec += carry
    us -= carry * 1_000_000
    for k in np.flatnonzero(near).tolist():
        w, _, frac = f"{t[k]:f}".partition(".")
        sec[k], us[k] = int(w), int(frac)
    return sec, us


def _candump_bytes(block: FrameBlock, channel: bytes) -> bytes:
    """The candump lines of a block, formatted by the compiled kernel."""
    n = len(block)
    if n == 0:
        return b""
    split = _split_timestamps(block.t)
    if split is None:  # negative or huge timestamps: rare, formatted per row
        return _candump_lines(block, channel.decode("ascii")).encode("ascii")
    sec, usec = split
    width = block.data.shape[1]
    # "(" sec "." usec ") " channel " " id(<= 8) "#" "#0"? data "\n"
    longest = 1 + 16 + 1 + 6 + 2 + len(channel) + 1 + 8 + 1 + 2 + 2 * width + 1
    out = np.empty(n * longest, np.uint8)
    size = candump.format_lines(
        sec, usec, np.ascontiguousarray(block.arbitration_id, np.uint32),
        np.ascontiguousarray(block.is_extended, np.bool_),
        np.ascontiguousarray(block.is_remote, np.bool_),
        np.ascontiguousarray(block.is_error, np.bool_),
        np.ascontiguousarray(block.dlc, np.uint8), np.ascontiguousarray(block.data, np.uint8),
        np.frombuffer(channel, np.uint8), out)
    return out[:size].tobytes()


def check_channel(channel: object, what: str = "channel") -> str:
    """``channel`` if it is a channel name the candump reader takes back: 1 to
    :data:`MAX_CHANNEL` printable ASCII characters, no space; else
    :class:`~canrls.core.errors.LogFormatError` naming ``what``."""
    if not (isinstance(channel, str) and 0 < len(channel) <= MAX_CHANNEL
            and all("!" <= c <= "~" for c in channel)):
        raise LogFormatError(f"{what} {channel!r}: a channel name in a CAN log is 1 to "
                             f"{MAX_CHANNEL} printable ASCII characters without spaces "
                             f"(what the log readers take back)")
    return channel


def write_candump(path: str | os.PathLike[str], blocks: Iterable[FrameBlock],
                  channel: str = "can0", *, what: str | None = None) -> int:
    """Write blocks as a candump ``.log`` file (atomically: a fresh temporary beside it,
    then a rename; see :func:`canrls.core.files.atomic_writer`).

    Returns the number of frames written.
    """
    p = Path(path)
    ch = check_channel(channel).encode("ascii")
    n = 0
    with atomic_writer(p, what or str(p), LogFormatError) as f:
        for block in blocks:
            f.write(_candump_bytes(block, ch))
            n += len(block)
    return n


def write_log(path: str | os.PathLike[str], blocks: Iterable[FrameBlock],
              channel: str = "can0", *, what: str | None = None) -> int:
    """Write blocks in the format the suffix names: ``.log`` natively, ``.asc``,
    ``.blf``, ``.csv``, ``.trc`` through python-can's writers (atomically, as
    :func:`write_candump`)."""
    p = Path(path)
    label = what or str(p)
    if p.suffix.lower() == ".log":
        return write_candump(p, blocks, channel, what=label)
    check_channel(channel)
    n = 0
    with atomic_writer(p, label, LogFormatError) as f:
        try:
            writer = writer_on(f, p, label)
        except ConfigError as e:
            raise LogFormatError(str(e)) from e
        with writer:
            for block in blocks:
                for msg in block.to_messages(channel):
                    writer.on_message_received(msg)
                    n += 1
    return n
