"""Log reading and writing: candump natively, the other formats through python-can."""

from __future__ import annotations

from pathlib import Path

import can
import numpy as np
import pytest

from canrls.errors import LogFormatError
from canrls.frameblock import FrameBlock
from canrls.logs import LogReadStats, read_frames, write_candump, write_log


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
