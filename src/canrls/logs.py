"""Reading and writing CAN logs as streams of :class:`~canrls.frameblock.FrameBlock`.

Formats
-------
``.log``
    candump (``(1700000000.123456) can0 101#0011223344556677``). Parsed by canrls's
    own reader, vectorised with numpy over lines of the same layout, because the
    offline replay must reach millions of frames per second; lines of any other
    layout (remote frames ``R``, CAN FD ``##``, odd spacing) take a per-line path that
    follows python-can's ``CanutilsLogReader``. Both paths give the same frames.
``.asc``, ``.blf``, ``.trc``, ``.csv`` (and anything else ``can.LogReader`` knows)
    read through python-can's readers, packed into blocks.

Reading streams in blocks of ``chunk_size`` frames, so memory stays flat in the
log's length. A line that cannot be parsed is a :class:`~canrls.errors.LogFormatError`
naming the file and line number, unless ``skip_bad_lines=True`` (the named
opt-out), in which case it is counted in :attr:`LogReadStats.bad_lines`.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import can
import numpy as np
import numpy.typing as npt

from canrls.errors import LogFormatError
from canrls.frameblock import FrameBlock

__all__ = ["LogReadStats", "read_frames", "write_candump", "write_log", "CAN_ERR_FLAG"]

#: Linux SocketCAN error-frame flag in the 32-bit CAN ID (candump writes it in the ID).
CAN_ERR_FLAG = 0x20000000
_EFF_MASK = 0x1FFFFFFF

_HEX = np.full(256, 255, dtype=np.uint8)
for _c, _v in zip(b"0123456789", range(10), strict=True):
    _HEX[_c] = _v
for _c, _v in zip(b"ABCDEF", range(10, 16), strict=True):
    _HEX[_c] = _v
for _c, _v in zip(b"abcdef", range(10, 16), strict=True):
    _HEX[_c] = _v
_DIGIT = np.full(256, 255, dtype=np.uint8)
for _c, _v in zip(b"0123456789", range(10), strict=True):
    _DIGIT[_c] = _v


@dataclass
class LogReadStats:
    """What a read went through: frames, lines and bytes seen."""

    frames: int = 0
    lines: int = 0
    bad_lines: int = 0
    bytes_read: int = 0
    total_bytes: int = 0


def read_frames(
    path: str | os.PathLike[str],
    chunk_size: int = 65536,
    *,
    skip_bad_lines: bool = False,
    stats: LogReadStats | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> Iterator[FrameBlock]:
    """Yield the frames of a log file in blocks of at most about ``chunk_size`` frames.

    Parameters
    ----------
    path : log file (``.log`` candump, ``.asc``, ``.blf``, ``.trc``, ``.csv``, ...)
    chunk_size : frames per block (memory stays proportional to it)
    skip_bad_lines : count unparsable candump lines instead of raising
    stats : filled in while reading
    progress : called as ``progress(bytes_done, bytes_total)`` after each block
    """
    p = Path(path)
    if not p.is_file():
        raise LogFormatError(f"{p}: no such log file")
    st = stats if stats is not None else LogReadStats()
    st.total_bytes = p.stat().st_size
    if p.suffix.lower() == ".log":
        yield from _read_candump(p, chunk_size, skip_bad_lines, st, progress)
    else:
        yield from _read_python_can(p, chunk_size, st, progress)


# --------------------------------------------------------------------------- candump


def _read_candump(path: Path, chunk_size: int, skip_bad: bool, st: LogReadStats,
                  progress: Callable[[int, int], None] | None) -> Iterator[FrameBlock]:
    # ~40 bytes per line in a typical classic-CAN candump file
    read_bytes = max(4096, chunk_size * 40)
    line_no = 0
    with open(path, "rb") as f:
        tail = b""
        while True:
            buf = f.read(read_bytes)
            if not buf:
                data = tail
                tail = b""
            else:
                data = tail + buf
                cut = data.rfind(b"\n")
                if cut < 0:
                    tail = data
                    continue
                tail = data[cut + 1:]
                data = data[: cut + 1]
            if data:
                block, nlines = _parse_candump_bytes(data, path, line_no, skip_bad, st)
                line_no += nlines
                st.lines += nlines
                st.bytes_read += len(data)
                if len(block):
                    st.frames += len(block)
                    yield block
                if progress is not None:
                    progress(st.bytes_read, st.total_bytes)
            if not buf:
                break


def _parse_candump_bytes(data: bytes, path: Path, line0: int, skip_bad: bool,
                         st: LogReadStats) -> tuple[FrameBlock, int]:
    """Parse whole lines; returns the block and the number of lines consumed."""
    raw = np.frombuffer(data, dtype=np.uint8)
    nl = np.flatnonzero(raw == 10)
    if len(data) and data[-1:] != b"\n":
        nl = np.append(nl, len(raw))
    starts = np.empty(len(nl), dtype=np.int64)
    starts[0:1] = 0
    starts[1:] = nl[:-1] + 1
    ends = nl.copy()
    # strip a trailing carriage return
    cr = (ends > starts) & (raw[np.maximum(ends - 1, 0)] == 13)
    ends[cr] -= 1
    lengths = ends - starts
    nlines = len(starts)
    order_parts: list[np.ndarray] = []
    blocks: list[FrameBlock] = []
    slow: list[int] = []
    for length in np.unique(lengths):
        idx = np.flatnonzero(lengths == length)
        if length == 0:
            continue  # blank lines carry nothing
        got = _parse_group(raw, starts[idx], int(length))
        if got is None:
            slow.extend(idx.tolist())
            continue
        ok, block = got
        if not ok.all():
            slow.extend(idx[~ok].tolist())
            block = block.take(ok)
            idx = idx[ok]
        blocks.append(block)
        order_parts.append(idx)
    if slow:
        slow.sort()
        msgs: list[can.Message] = []
        kept: list[int] = []
        for k in slow:
            text = data[starts[k]:ends[k]].decode("ascii", errors="replace")
            if not text.strip() or text.lstrip().startswith("#"):
                continue
            try:
                msgs.append(_parse_candump_line(text))
                kept.append(k)
            except ValueError as e:
                if skip_bad:
                    st.bad_lines += 1
                    continue
                raise LogFormatError(
                    f"{path}:{line0 + k + 1}: not a candump line ({e}): {text[:80]!r}") from e
        if msgs:
            blocks.append(FrameBlock.from_messages(msgs))
            order_parts.append(np.asarray(kept, dtype=np.int64))
    if not blocks:
        return FrameBlock.empty(), nlines
    merged = FrameBlock.concat(blocks)
    order = np.argsort(np.concatenate(order_parts), kind="stable")
    return merged.take(order), nlines


def _parse_group(raw: npt.NDArray[np.uint8], starts: npt.NDArray[np.int64],
                 length: int) -> tuple[npt.NDArray[np.bool_], FrameBlock] | None:
    """Vectorised parse of lines that share one length (and, checked here, one layout)."""
    if length < 8:
        return None
    rows = raw[starts[:, None] + np.arange(length)[None, :]]
    first = rows[0]
    line = first.tobytes()
    # layout from the first line: "(" ts ")" " " channel " " id "#" data
    if line[:1] != b"(":
        return None
    close = line.find(b")")
    dot = line.find(b".", 0, close)
    sp2 = line.find(b" ", close + 2)
    hash_ = line.find(b"#", sp2)
    if close < 0 or dot < 0 or sp2 < 0 or hash_ < 0 or line[close + 1:close + 2] != b" ":
        return None
    id_len = hash_ - sp2 - 1
    nhex = length - hash_ - 1
    if id_len not in (3, 8) or nhex % 2 or nhex > 16:
        return None
    # every line must share the separators and the channel text of the first
    fixed_cols = np.r_[0, close, close + 1, np.arange(close + 2, sp2 + 1), hash_]
    ok = (rows[:, fixed_cols] == first[fixed_cols]).all(axis=1)
    ip = rows[:, 1:dot]
    fp = rows[:, dot + 1:close]
    idc = rows[:, sp2 + 1:hash_]
    dc = rows[:, hash_ + 1:]
    di, df, hi, hd = _DIGIT[ip], _DIGIT[fp], _HEX[idc], _HEX[dc]
    ok &= (di != 255).all(axis=1) & (df != 255).all(axis=1)
    ok &= (hi != 255).all(axis=1) & (hd != 255).all(axis=1)
    n = len(starts)
    ip_v = np.zeros(n, np.int64)
    for c in range(di.shape[1]):
        ip_v = ip_v * 10 + di[:, c]
    fp_v = np.zeros(n, np.int64)
    for c in range(df.shape[1]):
        fp_v = fp_v * 10 + df[:, c]
    scale = 10 ** df.shape[1]
    # (int * 10^d + frac) is exact in int64 and < 2**53; one correctly rounded division
    # then gives the same float as float("int.frac").
    t = (ip_v * scale + fp_v).astype(np.float64) / float(scale)
    ids = np.zeros(n, np.int64)
    for c in range(hi.shape[1]):
        ids = ids * 16 + hi[:, c]
    nbytes = nhex // 2
    b = FrameBlock.allocate(n, 8)
    b.t[:] = t
    ext = id_len == 8
    is_err = (ids & CAN_ERR_FLAG) != 0 if ext else np.zeros(n, np.bool_)
    b.arbitration_id[:] = (ids & _EFF_MASK).astype(np.uint32)
    b.is_extended[:] = ext & ~is_err
    b.is_error[:] = is_err
    b.dlc[:] = nbytes
    if nbytes:
        b.data[:, :nbytes] = hd[:, 0::2] * 16 + hd[:, 1::2]
    return ok, b


def _parse_candump_line(text: str) -> can.Message:
    """One candump line, the way python-can's CanutilsLogReader reads it."""
    parts = text.split()
    if len(parts) < 3 or not (parts[0].startswith("(") and parts[0].endswith(")")):
        raise ValueError("expected '(timestamp) channel frame'")
    timestamp = float(parts[0][1:-1])
    channel = parts[1]
    frame = parts[2]
    if "#" not in frame:
        raise ValueError("frame has no '#'")
    can_id_s, rest = frame.split("#", 1)
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
    is_error = len(can_id_s) > 3 and bool(can_id & CAN_ERR_FLAG)
    return can.Message(timestamp=timestamp, channel=channel,
                       arbitration_id=can_id & _EFF_MASK,
                       is_extended_id=len(can_id_s) > 3 and not is_error,
                       is_remote_frame=is_remote, is_error_frame=is_error,
                       is_fd=is_fd, dlc=len(data), data=data)


# --------------------------------------------------------------------------- python-can readers


def _read_python_can(path: Path, chunk_size: int, st: LogReadStats,
                     progress: Callable[[int, int], None] | None) -> Iterator[FrameBlock]:
    try:
        reader = can.LogReader(str(path))
    except (ValueError, OSError, NotImplementedError) as e:
        raise LogFormatError(f"{path}: cannot read this log format ({e})") from e
    buf: list[can.Message] = []
    try:
        with reader:
            it = iter(reader)
            while True:
                try:
                    msg = next(it)
                except StopIteration:
                    break
                except Exception as e:  # python-can readers raise many kinds on bad input
                    raise LogFormatError(
                        f"{path}: unreadable after frame {st.frames + len(buf)} ({e})") from e
                buf.append(msg)
                if len(buf) >= chunk_size:
                    st.frames += len(buf)
                    yield FrameBlock.from_messages(buf)
                    buf = []
                    if progress is not None:
                        progress(min(st.frames, st.total_bytes), st.total_bytes)
    finally:
        pass
    if buf:
        st.frames += len(buf)
        yield FrameBlock.from_messages(buf)
    st.bytes_read = st.total_bytes
    if progress is not None:
        progress(st.total_bytes, st.total_bytes)


# --------------------------------------------------------------------------- writing


def _candump_lines(block: FrameBlock, channel: str) -> str:
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


def write_candump(path: str | os.PathLike[str], blocks: Iterable[FrameBlock],
                  channel: str = "can0") -> int:
    """Write blocks as a candump ``.log`` file (atomically: temp file, then rename).

    Returns the number of frames written.
    """
    p = Path(path)
    tmp = p.with_name(p.name + ".part")
    n = 0
    try:
        with open(tmp, "w", encoding="ascii", newline="\n") as f:
            for block in blocks:
                f.write(_candump_lines(block, channel))
                n += len(block)
        os.replace(tmp, p)
    finally:
        if tmp.exists():
            tmp.unlink()
    return n


def write_log(path: str | os.PathLike[str], blocks: Iterable[FrameBlock],
              channel: str = "can0") -> int:
    """Write blocks in the format the suffix names: ``.log`` natively, others via python-can."""
    p = Path(path)
    if p.suffix.lower() == ".log":
        return write_candump(p, blocks, channel)
    n = 0
    try:
        writer = can.Logger(str(p))
    except ValueError as e:
        raise LogFormatError(f"{p}: cannot write this log format ({e})") from e
    with writer:
        for block in blocks:
            for msg in block.to_messages(channel):
                writer.on_message_received(msg)
                n += 1
    return n
