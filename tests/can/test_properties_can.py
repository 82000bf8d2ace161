"""Property tests of the CAN layer's edges: whatever arrives, only canrls errors come out.

Random candump text and bytes through the log reader, random frames through the strict
decoder, the pairer and the reorderer, random estimator/status/command frames through
:class:`~canrls.can.estimator_frames.FrameDecoder`: each either works or raises a
:class:`~canrls.core.errors.CanrlsError` (one line, naming what failed); nothing else escapes.
"""

from __future__ import annotations

import math
from pathlib import Path

import can
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from canrls.can.decoder import Decoder
from canrls.can.estimator_frames import FrameDecoder, decode_command, frame_ids
from canrls.can.frameblock import FrameBlock
from canrls.can.logs import LogReadStats, read_frames
from canrls.can.protocol import Protocol
from canrls.core.errors import CanrlsError, LogFormatError
from canrls.processor.pairing import Pairer
from canrls.processor.reorder import Reorderer

PROPS = settings(max_examples=150, deadline=None,
                 suppress_health_check=[HealthCheck.function_scoped_fixture])
PROTOCOL = Protocol.load()
IDS = frame_ids()

_STAMPS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.floats(0, 2e9).map(lambda x: f"{x:.6f}"),
    st.sampled_from(["inf", "-inf", "nan", "1e300", "-0", ".5", "1.", "", "12345678901234567.1",
                     "0x10", "1_000.5"]),
    st.text("0123456789.-+eE", max_size=24))
_IDS_TEXT = st.one_of(st.sampled_from(["101", "102", "311", "1FFFFFFF", "20000080", "7FF"]),
                      st.text("0123456789ABCDEFabcdefxR#", max_size=10))
_DATA_TEXT = st.one_of(st.binary(max_size=8).map(lambda b: b.hex()),
                       st.sampled_from(["R", "#", "#0", "##1" + "00" * 12, "", "0", "G0"]),
                       st.text("0123456789ABCDEF#R .", max_size=20))


@st.composite
def candump_line(draw: st.DrawFn) -> str:
    shape = draw(st.integers(0, 3))
    if shape == 0:  # anything at all
        return draw(st.text(max_size=60)).replace("\n", " ")
    return (f"({draw(_STAMPS)}) {draw(st.sampled_from(['can0', 'vcan1', '', 'x y']))} "
            f"{draw(_IDS_TEXT)}#{draw(_DATA_TEXT)}")


@PROPS
@given(st.lists(candump_line(), max_size=12), st.booleans(), st.integers(1, 5))
def test_candump_text_reads_or_raises_a_log_format_error(tmp_path: Path, lines: list[str],
                                                         skip: bool, chunk: int) -> None:
    path = tmp_path / "random.log"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8", errors="replace")
    stats = LogReadStats()
    try:
        blocks = list(read_frames(path, chunk_size=chunk, skip_bad_lines=skip, stats=stats))
    except LogFormatError as e:
        assert not skip or "no such" in str(e)  # skipping reads past every bad line
        assert str(path) in str(e) and "\n" not in str(e)
        return
    got = FrameBlock.concat(blocks)
    # every timestamp read is a time: finite, not absurd
    assert np.all(np.isfinite(got.t)) and np.all(np.abs(got.t) <= 1e10)
    assert stats.frames == len(got)


@PROPS
@given(st.binary(max_size=400), st.sampled_from([".log", ".asc", ".trc", ".csv"]))
def test_random_bytes_read_or_raise_a_log_format_error(tmp_path: Path, data: bytes,
                                                       suffix: str) -> None:
    path = tmp_path / f"random{suffix}"
    path.write_bytes(data)
    try:
        got = FrameBlock.concat(read_frames(path, skip_bad_lines=suffix == ".log"))
    except CanrlsError as e:
        assert "\n" not in str(e)
        return
    assert np.all(np.isfinite(got.t)) and np.all(np.abs(got.t) <= 1e10)


@st.composite
def frame_blocks(draw: st.DrawFn) -> FrameBlock:
    n = draw(st.integers(0, 24))
    ids = st.sampled_from([0x101, 0x102, 0x101, 0x102, 0x300, 0x7FF, 0x1FFFFFFF])
    b = FrameBlock.allocate(n, 8)
    t0 = draw(st.floats(-1e3, 1e9))
    for k in range(n):
        b.t[k] = draw(st.one_of(st.just(t0 + 1e-3 * k), st.floats(-1e9, 1e9),
                                st.sampled_from([math.inf, -math.inf, math.nan])))
        b.arbitration_id[k] = draw(ids)
        b.is_extended[k] = b.arbitration_id[k] > 0x7FF
        b.is_remote[k] = draw(st.booleans()) and draw(st.booleans())
        b.is_error[k] = draw(st.booleans()) and draw(st.booleans())
        b.dlc[k] = draw(st.integers(0, 8))
        b.data[k] = np.frombuffer(draw(st.binary(min_size=8, max_size=8)), np.uint8)
    return b


@PROPS
@given(st.lists(frame_blocks(), max_size=4))
def test_random_frames_decode_pair_and_reorder_without_escaping_errors(
        blocks: list[FrameBlock]) -> None:
    dec, pr, ro = Decoder(PROTOCOL), Pairer(PROTOCOL), Reorderer(PROTOCOL.messages)
    n_in = n_out = 0
    for b in blocks:
        n_in += len(b)
        try:
            r = ro.push(b)
            n_out += len(r)
            pr.push(dec.decode(r))
        except CanrlsError:
            pass
    n_out += len(ro.flush())
    pr.flush()
    assert n_out == n_in  # the reorderer moves contents, never loses a frame


@PROPS
@given(st.lists(st.tuples(st.sampled_from(sorted(IDS.published | {IDS.command, IDS.ack, 0x55})),
                          st.binary(max_size=8), st.booleans(), st.booleans()), max_size=20))
def test_random_estimator_frames_feed_or_are_counted(msgs: list[tuple]) -> None:
    fd = FrameDecoder()
    for aid, data, remote, ext in msgs:
        m = can.Message(arbitration_id=aid, data=b"" if remote else data,
                        is_remote_frame=remote, is_extended_id=ext, dlc=len(data))
        fd.feed(m)  # never raises: malformed frames are counted
        if aid == IDS.command and not remote and not ext:
            try:
                decode_command(m)
            except CanrlsError as e:
                assert "\n" not in str(e)
    assert fd.malformed + fd.ignored <= len(msgs)


@pytest.mark.parametrize("stamp", ["inf", "1e300", "nan"])
def test_python_can_reader_rejects_an_absurd_timestamp(tmp_path: Path, stamp: str) -> None:
    """The same rule for a log python-can reads (.asc, .csv...): a LogFormatError."""
    path = tmp_path / "x.csv"
    path.write_text("timestamp,arbitration_id,extended,remote,error,dlc,data\n"
                    f"1.0,0x101,0,0,0,1,AA==\n{stamp},0x101,0,0,0,1,AA==\n")
    with pytest.raises(LogFormatError, match=r"x\.csv: frame 2 has the timestamp"):
        list(read_frames(path))
