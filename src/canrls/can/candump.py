"""Compiled candump kernels: bytes -> frame arrays, and frame arrays -> bytes.

Private to :mod:`canrls.can.logs`, which keeps a per-line Python path (following
python-can) for whatever these do not take:

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

import numba
import numpy as np
import numpy.typing as npt

from canrls.can import times

__all__ = ["parse", "format_lines", "CAN_ERR_FLAG", "EFF_MASK", "MAX_TIMESTAMP"]

#: Linux SocketCAN error-frame flag in the 32-bit CAN ID (candump writes it in the ID).
CAN_ERR_FLAG = 0x20000000
EFF_MASK = 0x1FFFFFFF

#: Largest timestamp [s] a log line may carry (:data:`canrls.can.times.MAX_TIMESTAMP`,
#: the one bound of live and offline): a line beyond it (``(1e300)``, ``(inf)``, a
#: corrupted time) is not a frame of this log but a bad line
#: (:class:`~canrls.errors.LogFormatError` naming the line, skippable with
#: ``skip_bad_lines``); the compiled parser hands such lines to the per-line path.
MAX_TIMESTAMP = times.MAX_TIMESTAMP

# exact powers of ten as doubles (10**22 is the largest exactly representable one)
_POW10 = np.array([10.0 ** k for k in range(23)], np.float64)
_HEXCHARS = np.frombuffer(b"0123456789ABCDEF", np.uint8).copy()
# value of a hex digit, -1 for any other byte
_HEXVAL = np.full(256, -1, np.int64)
for _k, _c in enumerate(b"0123456789ABCDEF"):
    _HEXVAL[_c] = _k
for _k, _c in enumerate(b"abcdef"):
    _HEXVAL[_c] = 10 + _k
#: most digits of a timestamp on the compiled path; the digits must also form an
#: integer of at most 2**53 (:data:`_MAX_EXACT`), an exact double
_MAX_DIGITS = 16
_MAX_EXACT = 2 ** 53


@numba.njit(cache=True, nogil=True)
def parse(buf: npt.NDArray[np.uint8], stop: int, final: bool,
          t: npt.NDArray[np.float64], aid: npt.NDArray[np.uint32],
          ext: npt.NDArray[np.bool_], err: npt.NDArray[np.bool_],
          dlc: npt.NDArray[np.uint8], data: npt.NDArray[np.uint8],
          slow: npt.NDArray[np.int64]) -> tuple[int, int, int, int]:  # pragma: no cover
    """Parse whole lines of ``buf[:stop]`` into the rows of the output arrays.

    Stops at the last complete line (``final``: the end of ``stop`` ends a line too)
    or when rows plus slow lines reach the capacity ``len(t)``. ``slow[k]`` =
    [row it precedes, start, end, line number] of the k-th slow line (end excludes
    the newline and a carriage return before it). ``data`` must be 8 bytes wide.

    Returns (bytes consumed, rows written, slow lines, lines consumed).
    """
    cap = t.shape[0]
    hexv = _HEXVAL
    pow10 = _POW10
    p = 0
    rows = 0
    nslow = 0
    lines = 0
    # layout of the last line parsed, relative to its start ``lay_p``: lines of a log
    # mostly share it, and a line that has it (checked byte by byte) is read at fixed
    # offsets without searching. lay_nl < 0: none yet.
    lay_p = 0
    lay_nl = -1
    lay_cr = False
    lay_dot = -1
    lay_close = 0
    lay_sp2 = 0
    lay_hash = 0
    while p < stop and rows + nslow < cap:
        if lay_nl >= 0:
            nl = p + lay_nl
            good = (nl < stop and buf[nl] == 10 and (buf[nl - 1] == 13) == lay_cr
                    and buf[p] == 40 and buf[p + lay_close] == 41
                    and buf[p + lay_close + 1] == 32 and buf[p + lay_sp2] == 32
                    and buf[p + lay_hash] == 35)
            num = 0
            if good:
                for i in range(1, lay_close):
                    c = np.int64(buf[p + i])
                    if i == lay_dot:
                        if c != 46:
                            good = False
                            break
                    elif 48 <= c <= 57:
                        num = num * 10 + (c - 48)
                    else:
                        good = False
                        break
                good = good and num <= _MAX_EXACT
            if good:
                for i in range(lay_close + 2, lay_sp2):  # the same channel
                    if buf[p + i] != buf[lay_p + i]:
                        good = False
                        break
            ident = 0
            if good:
                for i in range(lay_sp2 + 1, lay_hash):
                    v = hexv[buf[p + i]]
                    if v < 0:
                        good = False
                        break
                    ident = ident * 16 + v
            if good:
                d0 = p + lay_hash + 1
                nb = (lay_nl - lay_cr - lay_hash - 1) // 2
                bad = 0
                for j in range(nb):
                    hi = hexv[buf[d0 + 2 * j]]
                    lo = hexv[buf[d0 + 2 * j + 1]]
                    bad |= hi | lo
                    data[rows, j] = (hi * 16 + lo) & 255
                frac = lay_close - lay_dot - 1 if lay_dot >= 0 else 0
                if bad >= 0 and float(num) / pow10[frac] <= MAX_TIMESTAMP:
                    for j in range(nb, 8):
                        data[rows, j] = 0
                    nid = lay_hash - lay_sp2 - 1
                    t[rows] = float(num) / pow10[frac]
                    is_err = nid == 8 and (ident & CAN_ERR_FLAG) != 0
                    aid[rows] = ident & EFF_MASK
                    ext[rows] = nid == 8 and not is_err
                    err[rows] = is_err
                    dlc[rows] = nb
                    rows += 1
                    lines += 1
                    lay_p = p
                    p = nl + 1
                    continue
        e = p
        while e < stop and buf[e] != 10:
            e += 1
        if e == stop and not final:
            break
        nxt = e + 1
        cr = e > p and buf[e - 1] == 13
        if cr:  # "\r\n"
            e -= 1
        ok = False
        # "(" digits [. digits] ")"
        if e - p >= 8 and buf[p] == 40:
            q = p + 1
            num = 0
            nd = 0
            frac = 0
            dot = -1
            while q < e:
                c = buf[q]
                if 48 <= c <= 57:
                    num = num * 10 + (c - 48)
                    nd += 1
                    frac += dot >= 0
                elif c == 46 and dot < 0:
                    dot = q - p
                else:
                    break
                q += 1
            if (0 < nd <= _MAX_DIGITS and num <= _MAX_EXACT and q + 2 < e and buf[q] == 41
                    and buf[q + 1] == 32):
                close = q - p
                # " " channel (printable, no space) " "
                q += 2
                c0 = q
                while q < e and 33 <= buf[q] <= 126:
                    q += 1
                if c0 < q < e and buf[q] == 32:
                    sp2 = q - p
                    # 3 or 8 hex digits "#"
                    q += 1
                    i0 = q
                    ident = 0
                    while q < e:
                        v = hexv[buf[q]]
                        if v < 0:
                            break
                        ident = ident * 16 + v
                        q += 1
                    nid = q - i0
                    if (nid == 3 or nid == 8) and q < e and buf[q] == 35:
                        hash_ = q - p
                        # 0..8 data bytes, two hex digits each, to the end of the line
                        q += 1
                        nhex = e - q
                        if nhex % 2 == 0 and nhex <= 16:
                            nb = nhex // 2
                            bad = 0
                            for j in range(nb):
                                hi = hexv[buf[q + 2 * j]]
                                lo = hexv[buf[q + 2 * j + 1]]
                                bad |= hi | lo
                                data[rows, j] = (hi * 16 + lo) & 255
                            if bad >= 0 and float(num) / pow10[frac] <= MAX_TIMESTAMP:
                                for j in range(nb, 8):
                                    data[rows, j] = 0
                                # float("int.frac"): (int * 10^d + frac) / 10^d, both
                                # exact doubles, one correctly rounded division
                                t[rows] = float(num) / pow10[frac]
                                is_err = nid == 8 and (ident & CAN_ERR_FLAG) != 0
                                aid[rows] = ident & EFF_MASK
                                ext[rows] = nid == 8 and not is_err
                                err[rows] = is_err
                                dlc[rows] = nb
                                ok = True
                                if nxt <= stop:
                                    # a newline ends it: remember the layout
                                    lay_p = p
                                    lay_nl = nxt - 1 - p
                                    lay_cr = cr
                                    lay_dot = dot
                                    lay_close = close
                                    lay_sp2 = sp2
                                    lay_hash = hash_
        if e > p:
            if ok:
                rows += 1
            else:
                slow[nslow, 0] = rows
                slow[nslow, 1] = p
                slow[nslow, 2] = e
                slow[nslow, 3] = lines
                nslow += 1
        lines += 1
        p = nxt
    return min(p, stop), rows, nslow, lines


@numba.njit(cache=True, nogil=True, inline="always")
def _put_uint(out, o, v, width):  # pragma: no cover - compiled
    """Decimal digits of v >= 0, at least ``width`` of them (zero-padded)."""
    n = 1
    x = v // 10
    while x > 0:
        n += 1
        x //= 10
    if n < width:
        n = width
    for k in range(n - 1, -1, -1):
        out[o + k] = 48 + v % 10
        v //= 10
    return o + n


@numba.njit(cache=True, nogil=True)
def format_lines(sec: npt.NDArray[np.int64], usec: npt.NDArray[np.int64],
                 aid: npt.NDArray[np.uint32], ext: npt.NDArray[np.bool_],
                 rtr: npt.NDArray[np.bool_], err: npt.NDArray[np.bool_],
                 dlc: npt.NDArray[np.uint8], data: npt.NDArray[np.uint8],
                 channel: npt.NDArray[np.uint8],
                 out: npt.NDArray[np.uint8]) -> int:  # pragma: no cover - compiled
    """Write ``(sec.usec) channel ID#DATA\\n`` per row into ``out``; return the length.

    ID: ``%08X`` of ``id | CAN_ERR_FLAG`` for error frames, ``%08X`` extended,
    ``%03X`` standard. DATA: ``R`` remote, ``0`` + hex after a second ``#`` beyond 8
    bytes (CAN FD), else the hex bytes. ``out`` must hold the longest line per row.
    """
    hexc = _HEXCHARS
    width = data.shape[1]
    o = 0
    for k in range(sec.shape[0]):
        out[o] = 40  # "("
        o = _put_uint(out, o + 1, sec[k], 1)
        out[o] = 46  # "."
        o = _put_uint(out, o + 1, usec[k], 6)
        out[o] = 41
        out[o + 1] = 32
        o += 2
        for j in range(channel.shape[0]):
            out[o + j] = channel[j]
        o += channel.shape[0]
        out[o] = 32
        o += 1
        cid = np.int64(aid[k])
        w = 3
        if err[k]:
            cid = cid | CAN_ERR_FLAG
            w = 8
        elif ext[k]:
            w = 8
        n = 1
        x = cid >> 4
        while x > 0:
            n += 1
            x >>= 4
        if n < w:
            n = w
        for j in range(n - 1, -1, -1):
            out[o + j] = hexc[cid & 15]
            cid >>= 4
        o += n
        out[o] = 35  # "#"
        o += 1
        d = np.int64(dlc[k])
        if rtr[k]:
            out[o] = 82  # "R"
            o += 1
        else:
            if d > 8:
                out[o] = 35
                out[o + 1] = 48
                o += 2
            if d > width:
                d = width
            for j in range(d):
                b = data[k, j]
                out[o] = hexc[b >> 4]
                out[o + 1] = hexc[b & 15]
                o += 2
        out[o] = 10
        o += 1
    return o
