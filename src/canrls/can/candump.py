"""The candump reader's and writer's loops: bytes -> frame arrays, and frame arrays -> bytes.

Private to :mod:`canrls.can.logs`, which keeps a per-line Python path (following
python-can) for whatever these do not take. The loops are C (``canrls._candump``,
``src/canrls/c/host/candump.c``):

parse
    ``(SECONDS.FRACTION) CHANNEL ID#DATA`` with a 3- or 8-digit hex ID and 0..8 data
    bytes, single spaces, an optional ``\\r`` before the ``\\n``. The timestamp is
    exact: its (at most 16) digits form an integer ``N <= 2**53`` (an epoch time of
    ``candump -l``, ``1700000000.123456``, has 16), and ``N / 10**d`` is
    one correctly rounded division of two exact doubles, which is what
    ``float("SECONDS.FRACTION")`` returns. Any other non-blank line (remote ``R``, CAN
    FD ``##``, IDs of other lengths, longer timestamps, odd spacing, comments, junk) is
    handed back as a "slow" line, with the row it belongs before, so that the caller
    keeps the file's order. A line with the layout of the line before it (the same
    length and separators at the same places, as almost every line of a log) is read
    at fixed offsets, every byte still checked.
format
    one line per frame exactly as ``f"({t:f}) {channel} {id}#{data}\\n"`` writes it;
    the timestamp arrives already split into exact integer seconds and microseconds
    (negative or huge timestamps are formatted in Python).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from canrls import _candump

__all__ = ["parse", "format_lines", "CAN_ERR_FLAG", "EFF_MASK"]

#: Linux SocketCAN error-frame flag in the 32-bit CAN ID (candump writes it in the ID).
CAN_ERR_FLAG: int = _candump.CAN_ERR_FLAG
EFF_MASK: int = _candump.EFF_MASK



def parse(buf: npt.NDArray[np.uint8], stop: int, final: bool,
          t: npt.NDArray[np.float64], aid: npt.NDArray[np.uint32],
          ext: npt.NDArray[np.bool_], err: npt.NDArray[np.bool_],
          dlc: npt.NDArray[np.uint8], data: npt.NDArray[np.uint8],
          slow: npt.NDArray[np.int64]) -> tuple[int, int, int, int]:
    """Parse whole lines of ``buf[:stop]`` into the rows of the output arrays.

    Stops at the last complete line (``final``: the end of ``stop`` ends a line too)
    or when rows plus slow lines reach the capacity ``len(t)``. ``slow[k]`` =
    [row it precedes, start, end, line number] of the k-th slow line (end excludes
    the newline and a carriage return before it). ``data`` must be 8 bytes wide.

    Returns (bytes consumed, rows written, slow lines, lines consumed).
    """
    return _candump.parse(buf, stop, final, t, aid, ext, err, dlc, data, slow)


def format_lines(sec: npt.NDArray[np.int64], usec: npt.NDArray[np.int64],
                 aid: npt.NDArray[np.uint32], ext: npt.NDArray[np.bool_],
                 rtr: npt.NDArray[np.bool_], err: npt.NDArray[np.bool_],
                 dlc: npt.NDArray[np.uint8], data: npt.NDArray[np.uint8],
                 channel: npt.NDArray[np.uint8], out: npt.NDArray[np.uint8]) -> int:
    """Write ``(sec.usec) channel ID#DATA\\n`` per row into ``out``; return the length.

    ID: ``%08X`` of ``id | CAN_ERR_FLAG`` for error frames, ``%08X`` extended,
    ``%03X`` standard. DATA: ``R`` remote, ``0`` + hex after a second ``#`` beyond 8
    bytes (CAN FD), else the hex bytes. ``sec`` and ``usec`` must be ``>= 0``; ``out``
    must hold every line (``ValueError`` otherwise, nothing written beyond it).
    """
    return _candump.format_lines(sec, usec, aid, ext, rtr, err, dlc, data, channel, out)
