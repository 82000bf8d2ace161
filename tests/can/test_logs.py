"""Log reading and writing: candump natively, the other formats through python-can."""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest

from canrls.can import candump
from canrls.can.frameblock import FrameBlock
from canrls.can.logs import LogReadStats, read_frames, write_candump, write_log
from canrls.core.errors import LogFormatError
from canrls.core.files import ContentHash


def random_block(n: int, seed: int = 0) -> FrameBlock:
    rng = np.random.default_rng(seed)
    b = FrameBlock.allocate(n)
    b.t[:] = 1_700_000_000 + np.cumsum(rng.integers(1, 2000, n)) * 1e-6
    b.arbitration_id[:] = rng.choice([0x101, 0x102, 0x7FF, 0x1], n)
    b.dlc[:] = rng.integers(0, 9, n)
    b.data[:] = rng.integers(0, 256, (n, 8))
    for k in range(n):
        b.data[k, b.dlc[k]:] = 0
    return b


def same_frames(a: FrameBlock, b: FrameBlock) -> None:
    assert len(a) == len(b)
    np.testing.assert_array_equal(a.arbitration_id, b.arbitration_id)
    np.testing.assert_array_equal(a.dlc, b.dlc)
    np.testing.assert_array_equal(a.data[:, :8], b.data[:, :8])
    np.testing.assert_array_equal(a.is_extended, b.is_extended)
    np.testing.assert_allclose(a.t, b.t, rtol=0, atol=1e-6)


def test_candump_round_trip_and_agrees_with_python_can(tmp_path: Path) -> None:
    block = random_block(5000)
    path = tmp_path / "x.log"
    assert write_candump(path, [block]) == 5000
    mine = FrameBlock.concat(read_frames(path, chunk_size=700))
    same_frames(mine, block)
    ref = FrameBlock.from_messages(list(can.LogReader(str(path))))
    same_frames(mine, ref)
    np.testing.assert_array_equal(mine.t, ref.t)  # bit-identical timestamps


def test_candump_mixed_layouts_follow_python_can(tmp_path: Path) -> None:
    path = tmp_path / "mixed.log"
    path.write_text(
        "(1.000100) can0 101#0102\n"
        "(1.000200) can0 12345678#AABB\n"
        "(1.5) vcan1 7FF#R\n"
        "\n"
        "(3.000001) can0 102#1122334455667788\n"
        "(3.5) can0   102#11\n"
    )
    mine = FrameBlock.concat(read_frames(path)).to_messages()
    ref = list(can.LogReader(str(path)))
    assert len(mine) == len(ref) == 5
    for a, b in zip(mine, ref, strict=True):
        assert a.equals(b, timestamp_delta=1e-9, check_channel=False), (a, b)


def test_bad_candump_line_names_file_and_line(tmp_path: Path) -> None:
    path = tmp_path / "bad.log"
    path.write_text("(1.0) can0 101#0102\n(1.1) can0 101#01020\n(1.2) can0 zz#01\n")
    with pytest.raises(LogFormatError, match=r"bad\.log:2"):
        list(read_frames(path))
    stats = LogReadStats()
    frames = FrameBlock.concat(read_frames(path, skip_bad_lines=True, stats=stats))
    assert len(frames) == 1 and stats.bad_lines == 2 and stats.lines == 3


def test_missing_file_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(LogFormatError, match="no such log file"):
        list(read_frames(tmp_path / "nope.log"))


@pytest.mark.parametrize("suffix", [".asc", ".blf", ".csv", ".trc"])
def test_other_formats_through_python_can(tmp_path: Path, suffix: str) -> None:
    block = random_block(300, seed=3)
    block.t[:] -= block.t[0] - 1.0  # asc/trc store relative times
    path = tmp_path / f"x{suffix}"
    write_log(path, [block])
    got = FrameBlock.concat(read_frames(path, chunk_size=64))
    assert len(got) == 300
    np.testing.assert_array_equal(got.arbitration_id, block.arbitration_id)
    np.testing.assert_array_equal(got.data[:, :8], block.data[:, :8])


def test_progress_reaches_the_end(tmp_path: Path) -> None:
    path = tmp_path / "p.log"
    write_candump(path, [random_block(3000)])
    seen: list[tuple[int, int]] = []
    list(read_frames(path, chunk_size=100, progress=lambda d, t: seen.append((d, t))))
    assert len(seen) > 1 and seen[-1][0] == seen[-1][1] == path.stat().st_size


# ----------------------------------------------------------------- compiled candump paths


def _per_line(path: Path) -> tuple[FrameBlock, int, int]:
    """Reference: every line through the per-line reader (python-can's rules).

    Returns the frames, the number of lines and of unreadable lines.
    """
    from canrls.can.logs import _parse_candump_line

    raw = path.read_bytes().split(b"\n")
    if raw[-1] == b"":
        raw.pop()
    msgs, bad = [], 0
    for line in raw:
        text = line.removesuffix(b"\r").decode("ascii", errors="replace")
        if not text.strip() or text.lstrip().startswith("#"):
            continue
        try:
            msgs.append(_parse_candump_line(text))
        except ValueError:
            bad += 1
    return FrameBlock.from_messages(msgs), len(raw), bad


def _identical(a: FrameBlock, b: FrameBlock) -> None:
    assert len(a) == len(b)
    for name in ("t", "arbitration_id", "is_extended", "is_remote", "is_error", "dlc"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    w = max(a.data.shape[1], b.data.shape[1])
    np.testing.assert_array_equal(np.pad(a.data, ((0, 0), (0, w - a.data.shape[1]))),
                                  np.pad(b.data, ((0, 0), (0, w - b.data.shape[1]))))


@pytest.mark.parametrize("seed", range(6))
def test_compiled_reader_agrees_with_the_per_line_reader_on_damaged_lines(
        tmp_path: Path, seed: int) -> None:
    """Regular lines (one layout) with single bytes damaged: every line, whichever path
    takes it, reads as the per-line reader reads it; damaged lines are counted."""
    rng = np.random.default_rng(seed)
    n = 2000
    t = np.cumsum(rng.integers(1, 300, n)) * 1e-4 + [0.0, 9.9, 99999.0][seed % 3]
    end = "\r" if seed % 2 else ""
    lines = [f"({t[k]:.6f}) can0 {'101' if k % 2 else '102'}#{rng.bytes(8).hex().upper()}{end}"
             for k in range(n)]
    alphabet = b"0123456789abcdefABCDEFxyz .#()R\r\t-+e"
    for k in rng.choice(n, 80, replace=False):
        b = bytearray(lines[k].encode())
        b[rng.integers(0, len(b))] = alphabet[rng.integers(0, len(alphabet))]
        lines[k] = b.decode()
    lines[5] = "(1.0) can1 101#0011"           # another channel and length
    lines[6] = lines[7].replace("can0", "can1")  # another channel, same length
    path = tmp_path / "damaged.log"
    path.write_bytes(("\n".join(lines) + ("\n" if seed % 3 else "")).encode())
    ref, n_lines, n_bad = _per_line(path)
    for chunk in (1, 7, 999, 65536):
        stats = LogReadStats()
        got = FrameBlock.concat(read_frames(path, chunk, skip_bad_lines=True, stats=stats))
        _identical(got, ref)
        assert (stats.frames, stats.lines, stats.bad_lines) == (len(ref), n_lines, n_bad)
        assert stats.bytes_read == path.stat().st_size


def test_candump_odd_but_valid_lines_follow_python_can(tmp_path: Path) -> None:
    path = tmp_path / "odd.log"
    path.write_bytes(
        b"(1700000000.123456) can0 101#0a0b\r\n"       # CRLF, lower-case hex
        b"(1.1111111111111111111111111) can0 101#\n"    # more digits than a double holds
        b"(1234567890.1234567891) can0 1FFFFFFF#01\n"  # digits beyond 2**53
        b"(7) vcan1 7FF#0102030405060708\n"             # no fraction
        b"(.5) can0 123#11\n"                           # no integer part
        b"(2.5) can0 12345678##0001122334455667788990011\n"  # CAN FD, 12 bytes
        b"(3.25) can0 101#R\n"                          # remote
        b"(4.0) can0 101#00")                           # no newline at the end
    got = FrameBlock.concat(read_frames(path, chunk_size=3)).to_messages()
    ref = list(can.LogReader(str(path)))
    assert len(got) == len(ref) == 8
    for a, b in zip(got, ref, strict=True):
        assert a.timestamp == b.timestamp  # bit-identical
        assert a.equals(b, timestamp_delta=None, check_channel=False), (a, b)


def test_candump_line_longer_than_the_read_buffer(tmp_path: Path) -> None:
    path = tmp_path / "long.log"
    path.write_text("(1.0) can0 101#01\n# " + "x" * 300_000 + "\n(2.0) can0 102#02\n")
    stats = LogReadStats()
    got = FrameBlock.concat(read_frames(path, chunk_size=2, stats=stats))
    assert got.t.tolist() == [1.0, 2.0] and stats.lines == 3


def _format_reference(block: FrameBlock, channel: str) -> str:
    """candump lines as ``f"({t:f}) {channel} {id}#{data}"`` writes them."""
    out = []
    for k in range(len(block)):
        cid = int(block.arbitration_id[k])
        if block.is_error[k]:
            ids = f"{cid | 0x20000000:08X}"
        else:
            ids = f"{cid:08X}" if block.is_extended[k] else f"{cid:03X}"
        n = int(block.dlc[k])
        body = block.data[k, :n].tobytes().hex().upper()
        body = "R" if block.is_remote[k] else ("#0" + body if n > 8 else body)
        out.append(f"({block.t[k]:f}) {channel} {ids}#{body}\n")
    return "".join(out)


@pytest.mark.parametrize("width", [8, 64])
def test_write_candump_formats_as_python_does(tmp_path: Path, width: int) -> None:
    rng = np.random.default_rng(width)
    n = 20_000
    b = FrameBlock.allocate(n, width)
    b.t[:] = np.cumsum(rng.integers(1, 2000, n)) * 1e-6 + rng.choice([0.0, 1.7e9, 12.3456785])
    b.t[::7] = np.round(b.t[::7], 6) + 5e-7          # halfway between two microseconds
    b.t[::11] = rng.integers(0, 10**6, len(b.t[::11])) / 2**20  # exact binary fractions
    b.arbitration_id[:] = rng.choice([0x0, 0x101, 0x7FF, 0x1234, 0x1FFFFFFF], n)
    b.is_extended[:] = rng.random(n) < 0.3
    b.is_error[:] = rng.random(n) < 0.05
    b.is_remote[:] = rng.random(n) < 0.05
    b.dlc[:] = rng.integers(0, width + 1, n)
    b.data[:] = rng.integers(0, 256, (n, width))
    path = tmp_path / "w.log"
    assert write_candump(path, [b.take(slice(0, 1234)), b.take(slice(1234, n))], "vcan0") == n
    assert path.read_text() == _format_reference(b, "vcan0")
    b.t[3] = -1.25  # negative timestamps take Python's formatting
    write_candump(path, [b], "vcan0")
    assert path.read_text() == _format_reference(b, "vcan0")


# --------------------------------------------- the C loops against the numba kernels
def candump_text(seed: int, lines: int) -> bytes:
    """Seeded candump text of every layout the parser meets: runs of one layout, epoch
    and zero-based times of 0 to 24 digits, 3-, 5- and 8-digit IDs, odd data, remote
    frames, doubled spaces, comments, blank lines, ``\\r\\n``, ``(inf)``."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(lines):
        ts = f"{rng.uniform(0, 2e9 if rng.random() < 0.5 else 100):.{rng.integers(0, 9)}f}"
        if rng.random() < 0.05:
            ts = "".join(rng.choice(list("0123456789"), int(rng.integers(1, 25))))
        ident = "".join(rng.choice(list("0123456789ABCDEFabcdef"),
                                   int(rng.choice([3, 8, 8, 3, 5]))))
        data = "".join(rng.choice(list("0123456789ABCDEF"), 2 * int(rng.integers(0, 10))))
        data += "G" if rng.random() < 0.03 else ""
        data = "R" if rng.random() < 0.02 else data
        sep = "  " if rng.random() < 0.02 else " "
        line = f"({ts}){sep}{rng.choice(['can0', 'vcan12', 'x'])} {ident}#{data}"
        line = "# comment" if rng.random() < 0.02 else line
        line = "" if rng.random() < 0.02 else line
        line = "(inf) can0 123#00" if rng.random() < 0.01 else line
        end = "\r\n" if rng.random() < 0.05 else "\n"
        out += [line + end] * (2 if rng.random() < 0.7 else 1)
    return "".join(out).encode()


def candump_digest(parse: Any, format_lines: Any) -> str:
    """SHA-256 of what ``parse`` gives on :func:`candump_text` cut at random places (a
    line cut, the end of the buffer final or not, capacities of 1 to 400 rows) and of
    what ``format_lines`` writes for random blocks (8 and 64 bytes wide)."""
    rng = np.random.default_rng(5)
    h = hashlib.sha256()
    for k in range(200):
        buf = np.frombuffer(candump_text(k, int(rng.integers(1, 200))), np.uint8).copy()
        cap = int(rng.integers(1, 400))
        stop = int(rng.integers(0, len(buf) + 1)) if rng.random() < 0.5 else len(buf)
        out = [np.full(cap, -1.0), np.zeros(cap, np.uint32), np.zeros(cap, np.bool_),
               np.zeros(cap, np.bool_), np.zeros(cap, np.uint8), np.full((cap, 8), 7, np.uint8),
               np.full((cap, 4), -5, np.int64)]
        r = parse(buf, stop, bool(rng.random() < 0.5), *out)
        h.update(repr(tuple(int(x) for x in r)).encode())
        for a in out[:6]:
            h.update(a[:r[1]].tobytes())
        h.update(out[6][:r[2]].tobytes())
    for _ in range(100):
        n, width = int(rng.integers(1, 300)), int(rng.choice([8, 8, 64]))
        ext, rtr, err = rng.random(n) < 0.5, rng.random(n) < 0.1, rng.random(n) < 0.1
        aid = rng.integers(0, 2**29, n).astype(np.uint32)
        aid[~ext & ~err] &= 0x7FF
        dlc = rng.integers(0, 16 if width == 64 else 9, n).astype(np.uint8)
        ch = np.frombuffer(rng.choice([b"can0", b"vcan1", b"c"]), np.uint8)
        out8 = np.zeros(n * (33 + len(ch) + 2 * width), np.uint8)
        size = format_lines(rng.integers(0, 5_000_000_000, n), rng.integers(0, 1_000_000, n),
                            aid, ext, rtr, err, dlc,
                            rng.integers(0, 256, (n, width)).astype(np.uint8), ch, out8)
        h.update(out8[:size].tobytes())
    return h.hexdigest()[:16]


def test_the_c_loops_give_the_numba_kernels_bytes() -> None:
    """The candump parser and writer in C (``canrls._candump``) give, byte for byte, what
    the numba kernels they replace gave (f79833d: ``canrls.can.candump``)."""
    assert candump_digest(candump.parse, candump.format_lines) == "bcc0022e799a44cd"


def test_the_c_parser_keeps_the_one_timestamp_bound() -> None:
    """The compiled parser hands a line beyond the bound to the per-line path: its bound
    is :data:`canrls.core.checks.MAX_TIMESTAMP`, the one of live and offline."""
    from canrls import _candump
    from canrls.core.checks import MAX_TIMESTAMP

    assert _candump.MAX_TIMESTAMP == MAX_TIMESTAMP


def test_the_c_loops_refuse_wrong_arrays() -> None:
    buf = np.frombuffer(b"(1.0) can0 123#00\n", np.uint8)
    rows = [np.empty(4), np.empty(4, np.uint32), np.empty(4, np.bool_), np.empty(4, np.bool_),
            np.empty(4, np.uint8), np.empty((4, 8), np.uint8), np.empty((4, 4), np.int64)]
    assert candump.parse(buf, len(buf), True, *rows)[:3] == (len(buf), 1, 0)
    with pytest.raises(ValueError, match="stop 99 is outside buf"):
        candump.parse(buf, 99, True, *rows)
    with pytest.raises(ValueError, match="data must have shape"):
        candump.parse(buf, len(buf), True, *rows[:5], np.empty((4, 6), np.uint8), rows[6])
    with pytest.raises(TypeError, match="aid must be a uint32"):
        candump.parse(buf, len(buf), True, rows[0], np.empty(4, np.int64), *rows[2:])
    one = [np.zeros(1, np.int64), np.zeros(1, np.int64), np.zeros(1, np.uint32),
           *(np.zeros(1, np.bool_) for _ in range(3)), np.full(1, 8, np.uint8),
           np.zeros((1, 8), np.uint8), np.frombuffer(b"can0", np.uint8)]
    with pytest.raises(ValueError, match="out is too small"):
        candump.format_lines(*one, np.empty(20, np.uint8))
    # "(0.000000) can0 000#" and 16 digits and a newline
    assert candump.format_lines(*one, np.empty(40, np.uint8)) == 37


# --------------------------------------------------------------------------- read ahead
def test_reading_ahead_gives_the_blocks_and_counts_of_reading_in_turn(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Blocks of READ_AHEAD frames or more are parsed a block ahead in a thread: the same
    blocks, with lines of every layout (slow lines included), and the same counts after
    each block; a reader left early joins its thread and closes the file."""
    from canrls.can import logs

    path = tmp_path / "a.log"
    path.write_bytes(candump_text(3, 5000))
    runs = []
    for ahead in (1000, 10**12):  # blocks of 1,000 frames read ahead / in turn
        monkeypatch.setattr(logs, "READ_AHEAD", ahead)
        st = LogReadStats()
        seen = []
        for b in read_frames(path, 1000, skip_bad_lines=True, stats=st):
            seen.append((b, (st.frames, st.lines, st.bad_lines, st.slow_lines,
                             st.bytes_read)))
        runs.append(seen)
    assert len(runs[0]) == len(runs[1]) > 3
    for (a, sa), (b, sb) in zip(*runs, strict=True):
        _identical(a, b)
        assert sa == sb
    monkeypatch.setattr(logs, "READ_AHEAD", 1)
    reader = read_frames(path, 64, skip_bad_lines=True)
    next(reader)
    reader.close()  # the thread making the next block is joined (no leaked thread)


@pytest.mark.parametrize(("suffix", "chunk"), [(".log", 100), (".log", 65536), (".asc", 500),
                                               (".blf", 500)])
def test_a_digest_taken_while_reading_is_the_files_hash(tmp_path: Path, suffix: str,
                                                         chunk: int) -> None:
    """``digest=`` hashes every byte of the file as the frames are read (a candump log
    through the parser's reads, in turn or read ahead in a thread; another format after
    its frames): the SHA-256 of the file, complete only once the last block is read."""
    path = tmp_path / f"x{suffix}"
    write_log(path, [random_block(3000, seed=5)])
    with open(path, "ab") as f:
        f.write(b"\n" if suffix == ".log" else b"")  # a trailing line without a frame
    whole = hashlib.sha256(path.read_bytes()).hexdigest()
    d = ContentHash()
    blocks = read_frames(path, chunk, digest=d)
    frames = len(next(blocks))
    with pytest.raises(RuntimeError, match="not read to its end"):
        d.hexdigest()
    frames += sum(len(b) for b in blocks)
    assert frames == 3000
    assert d.hexdigest() == whole


@pytest.mark.parametrize("can_id", ["1000000101", "FFFFFFFFF", "0" * 40 + "101"])
def test_a_candump_id_of_more_than_8_digits_is_a_bad_line(tmp_path: Path,
                                                           can_id: str) -> None:
    """candump writes 3 or 8 hex digits; a longer ID was masked to 29 bits and read as
    another frame ("1000000101" as the extended 0x101), where the other formats refuse
    an ID beyond 29 bits (docs/reliability.md)."""
    path = tmp_path / "long_id.log"
    path.write_text(f"(1.0) can0 101#0102\n(1.1) can0 {can_id}#0102\n")
    with pytest.raises(LogFormatError, match=rf"long_id\.log:2: not a candump line \(the "
                                             rf"ID '.*' has {len(can_id)} hex digits"):
        list(read_frames(path))
    stats = LogReadStats()
    frames = FrameBlock.concat(read_frames(path, skip_bad_lines=True, stats=stats))
    assert len(frames) == 1 and stats.bad_lines == 1
