"""Strict decoding of blocks of frames with the mapped messages' codecs: :class:`Decoder`,
its rejections counted by reason (:class:`RejectCounts`) and the decoded values
(:class:`DecodedFrames`)."""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from canrls import _can
from canrls.can.codec import (
    CRC8_POWERS,
    PHYS_INT,
    MessageCodec,
    RoleInfo,
    SignalCodec,
    crc_vector,
    format_value,
)
from canrls.can.frameblock import FrameBlock

if TYPE_CHECKING:
    from canrls.can.protocol import Protocol

__all__ = ["REJECT_REASONS", "DecodedFrames", "Decoder", "MessageFrames", "RejectCounts"]

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]
U8 = npt.NDArray[np.uint8]

#: Rejection reasons, in the order the checks run (a frame counts under the first that fails).
REJECT_REASONS: tuple[str, ...] = (
    "error_frame",  # a CAN error frame (bus error, bus-off notification)
    "remote",       # a remote frame carrying a mapped message's ID
    "length",       # DLC differs from the DBC message length
    "crc",          # E2E CRC mismatch
    "repeated",     # same alive counter as the previous accepted frame of the message
    "stale",        # counter jumped backwards (by less than half its range)
    "sequence",     # counter jumped further ahead than the time since the last frame allows
    "nan",          # a float signal is NaN or infinite
    "range",        # a physical value lies outside the DBC [minimum, maximum]
    "time",         # the receive time is no time of the stream (canrls.processor.times): judged
                    # first, by the front end, before decoding; listed last, so that the
                    # codes of the others stay
)
_R = {r: k + 1 for k, r in enumerate(REJECT_REASONS)}  # reason -> code (0 = accepted)
_NO_REJECTS = dict.fromkeys(REJECT_REASONS, 0)


class RejectCounts(Mapping[str, int]):
    """Rejected frames: a mapping reason -> count (every reason of :data:`REJECT_REASONS`).

    ``per_message[name][reason]`` splits the counts by message (error frames, which
    belong to no message, are filed under ``"*"``); ``examples[reason]`` keeps the
    earliest (in stream order) human-readable example of each reason, e.g.
    ``"DriveSpeed.Speed = 830.5 rad/s outside [-800, 800] (t=1.234000 s)"``.
    """

    def __init__(self) -> None:
        self._counts: dict[str, int] = _NO_REJECTS.copy()
        self.per_message: dict[str, dict[str, int]] = {}
        self.examples: dict[str, str] = {}
        self._example_key: dict[str, int] = {}

    def __getitem__(self, reason: str) -> int:
        return self._counts[reason]

    def __iter__(self) -> Iterator[str]:
        return iter(self._counts)

    def __len__(self) -> int:
        return len(self._counts)

    @property
    def total(self) -> int:
        return sum(self._counts.values())

    def add(self, reason: str, message: str, n: int = 1, example: str | None = None,
            key: int = 0) -> None:
        """Count ``n`` rejections; ``example`` is kept if it is the earliest (smallest ``key``)."""
        if n <= 0:
            return
        self._counts[reason] += n
        per = self.per_message.setdefault(message, dict.fromkeys(REJECT_REASONS, 0))
        per[reason] += n
        if example is not None and self.wants_example(reason, key):
            self.examples[reason] = example
            self._example_key[reason] = key

    def wants_example(self, reason: str, key: int) -> bool:
        """True when an example of ``reason`` at position ``key`` would replace the kept one."""
        return reason not in self._example_key or key < self._example_key[reason]

    def merge(self, other: RejectCounts) -> None:
        """Add ``other``'s counts (and its examples where they come earlier) into this one."""
        for msg, per in other.per_message.items():
            for reason, n in per.items():
                self.add(reason, msg, n)
        for reason, ex in other.examples.items():
            key = other._example_key[reason]
            if self.wants_example(reason, key):
                self.examples[reason] = ex
                self._example_key[reason] = key

    def summary(self) -> str:
        """One line per reason with a non-zero count, with its example."""
        lines = []
        for r in REJECT_REASONS:
            if self._counts[r]:
                ex = self.examples.get(r)
                lines.append(f"{r}: {self._counts[r]}" + (f"  e.g. {ex}" if ex else ""))
        return "\n".join(lines)

    def __repr__(self) -> str:
        nz = {r: n for r, n in self._counts.items() if n}
        return f"RejectCounts({nz})"


@dataclass(frozen=True, init=False)
class MessageFrames:
    """The accepted frames of one mapped message in a block.

    ``index`` is each frame's position in the whole stream (0-based, across blocks),
    ``counter`` the raw alive counter (0 .. ``counter_modulo``-1) or, when the message
    has none, a running sequence number of its accepted frames (``counter_modulo`` is
    then ``None``); ``values`` maps each role of the message to SI values.
    """

    name: str
    t: F64
    index: I64
    counter: I64
    values: dict[str, F64]
    counter_modulo: int | None

    def __init__(self, name: str, t: F64, index: I64, counter: I64, values: dict[str, F64],
                 counter_modulo: int | None) -> None:
        # the fields go straight into the instance dict: a frozen dataclass's own
        # __init__ sets each through object.__setattr__, microseconds per live block
        d = self.__dict__
        d["name"], d["t"], d["index"], d["counter"] = name, t, index, counter
        d["values"], d["counter_modulo"] = values, counter_modulo

    def __len__(self) -> int:
        return len(self.t)


@dataclass(frozen=True, init=False)
class DecodedFrames:
    """Result of decoding one block: the accepted frames of each mapped message and the counts.

    ``rejected`` and ``lost`` (message -> frames missing according to the counter) and
    ``foreign`` (frames of other IDs, ignored) count this block only; the
    :class:`Decoder` keeps running totals.
    """

    messages: dict[str, MessageFrames]
    rejected: RejectCounts
    lost: dict[str, int]
    foreign: int

    def __init__(self, messages: dict[str, MessageFrames], rejected: RejectCounts,
                 lost: dict[str, int], foreign: int) -> None:
        d = self.__dict__  # as MessageFrames.__init__
        d["messages"], d["rejected"], d["lost"], d["foreign"] = messages, rejected, lost, foreign

    def __getitem__(self, name: str) -> MessageFrames:
        return self.messages[name]

    def __iter__(self) -> Iterator[MessageFrames]:
        return iter(self.messages.values())

    @property
    def accepted(self) -> int:
        return sum(len(m) for m in self.messages.values())


_STATUS_OK, _STATUS_REPEATED, _STATUS_STALE, _STATUS_SEQUENCE = 0, 1, 2, 3

#: columns of the counter state of one message (:func:`_counter_kernel`), then the
#: running sequence number of a message without counter (``Decoder._counters``)
_ST_COUNTER_COLS, _ST_COLS = 5, 6


def _counter_kernel(c: I64, t: F64, mod: int, window: int, period: float,
                    state: I64, state_t: F64, skip: npt.NDArray[np.bool_] | None = None,
                    ) -> tuple[npt.NDArray[np.int8], I64]:
    """Classify alive counters one frame at a time (``counter_step`` in
    ``src/canrls/c/host/can.c``), carrying state across blocks: state = [last counter (-1:
    none yet), run, counter of the last frame of the run, skipped, trusted]; state_t =
    [time of the last accepted frame]. Returns the status and the frames lost before
    each frame. Frames marked in ``skip`` (rejected before the counter check: length,
    CRC) are received but not classified (status 0, lost 0): they count as skipped.

    Per frame, counter ``c`` received at ``t``: d = (c - last) mod M; with dt the time
    since the last accepted frame and T the period (0: none),

    * d == 0 is ``repeated``, unless dt >= (M - 0.5) T (the counter went round);
    * d >= M - window is ``stale`` (a jump backwards), unless dt >= (d - 0.5) T;
    * 2 <= d < M - window is ``sequence`` (a wrong counter, not a loss: the AUTOSAR E2E
      receiver's wrong sequence) when the time says fewer periods passed, dt < (d -
      0.5) T, and the last accepted frame's time agreed with its counter (``trusted``:
      |dt - gap T| < T / 2 when it was accepted; a frame swapped with its neighbour
      arrives a period late and says nothing of the next one's time);
    * otherwise the frame is accepted: gap = d, plus k M when the time implies k =
      floor((dt / T - d) / M + 0.5) > 0 whole wraps and agrees with them, |dt / T - d -
      k M| < 1/2 (only for dt up to 1 s, :data:`canrls.processor.pairing.FORWARD_STEP`: a
      longer jump is a clock step or a silence as long, and the time says nothing of the
      frames lost in it; a shorter one off the wraps by more is a clock step too), and
      ``lost = max(0, gap - 1 - skipped)``: the frames of the message rejected since the
      last accepted one (``skipped``: stale, sequence, repeated half a period or more
      after the frame it repeats (with a period; a copy arriving with it takes no place
      in the sequence), and those marked in ``skip``) were received, not lost.

    A rejected frame leaves the state as it was, so the next good frame continues the
    sequence of the last accepted one: one wrong counter costs one frame. ``run``
    counts consecutive frames rejected for their counter that count up by one: a
    ``sequence`` frame that continues the one before it is accepted (the jump was a
    loss after all: timestamps bunched by the receiver), three ``stale`` ones
    resynchronise (loss unknown). Without a period, a forward jump is always a loss.
    """
    n = len(c)
    status = np.empty(n, np.uint8)
    lost = np.empty(n, np.int64)
    st = np.ascontiguousarray(state, np.int64)
    st_t = np.ascontiguousarray(state_t, np.float64)
    _can.counters(np.ascontiguousarray(c, np.int64), np.ascontiguousarray(t, np.float64),
                  int(mod), int(window), float(period), st, st_t, status, lost,
                  None if skip is None else np.ascontiguousarray(skip, np.bool_))
    if st is not state:
        state[:] = st
    if st_t is not state_t:
        state_t[:] = st_t
    return status.view(np.int8), lost


def _select_rows(arbitration_id: npt.NDArray[np.uint32], is_extended: npt.NDArray[np.bool_],
                 is_error: npt.NDArray[np.bool_], frame_id: int, extended: bool,
                 mine: npt.NDArray[np.bool_]) -> npt.NDArray[np.intp]:
    """Rows with this ID and format that are not error frames (marked in ``mine``)."""
    rows = (arbitration_id == frame_id) & (is_extended == extended) & ~is_error
    mine |= rows
    return np.flatnonzero(rows)


def _gather_check(data: U8, rows: npt.NDArray[np.intp], length: int,
                  is_remote: npt.NDArray[np.bool_], dlc: U8, check_crc: bool, frame_id: int,
                  powers: U8, out: U8, flags: U8) -> int:
    """Copy ``data[rows, :length]`` into ``out``; flag the first check each row fails:
    1 remote, 2 length (DLC), 4 CRC (only when ``check_crc``). Returns the flagged rows.
    """
    c = np.ascontiguousarray  # a no-op for the arrays of a FrameBlock
    d = c(data, np.uint8)
    return int(_can.gather_check(d, d.shape[1], c(rows, np.int64), length,
                                 c(is_remote, np.bool_), c(dlc, np.uint8), check_crc,
                                 frame_id, powers, out, flags))


def _counter_params(m: MessageCodec) -> tuple[int, int, float]:
    """Counter modulo M, stale window (half the range, less one) and period [s] (0: none)
    that :func:`_counter_kernel` takes for message ``m`` (which has a counter)."""
    modulo = int(m.counter_modulo or 0)
    return modulo, max(1, modulo // 2 - 1), float(m.cycle_time or 0.0)


# columns of _FastPlan.msg, one row per message
(_M_ID, _M_EXT, _M_LEN, _M_CRC, _M_CHECK, _M_MOD, _M_WINDOW, _M_COUNTER, _M_SIG0, _M_SIG1,
 _M_TROW, _M_COLS) = range(12)
# columns of _FastPlan.sig, one row per signal (the roles, then the counters): where the
# field is (bit _S_POS of the 64-bit little-endian word of payload bytes 0..7, or of the
# big-endian one when _S_BE), how it scales (SignalCodec.scaling) and the row of its SI
# values in the float output
(_S_SIGNED, _S_FLOAT, _S_MODE, _S_LEN, _S_BE, _S_POS, _S_SCALE, _S_OFFSET, _S_ROW,
 _S_COLS) = range(10)
# columns of _FastPlan.sig_f: float scale and offset, range limits in the DBC unit, SI factor
_F_SCALE, _F_OFFSET, _F_LO, _F_HI, _F_SI, _F_COLS = range(6)


class _NoFastPath(Exception):
    """A mapped signal that :func:`_fast_kernel` cannot decode (see :meth:`_FastPlan.build`)."""


class _FastPlan:
    """The constants of :func:`_fast_kernel` for one protocol and its options.

    ``msg`` / ``sig`` / ``sig_f`` are the packed message and signal tables (columns
    ``_M_*``, ``_S_*``, ``_F_*``); ``period`` the counters' periods [s]. The kernel
    writes, per message k, the times to row ``layout[k][1]`` of its float output and
    the SI values of the roles ``layout[k][2]`` to the rows after it, the stream indices
    and the counters to rows 2k and 2k + 1 of its integer output; ``counts`` receives
    the frames accepted (K) and lost (K) of each message, then the foreign frames.
    Build with :meth:`build`.

    The kernel takes each field from the 64-bit words of payload bytes 0..7 (one shift
    and mask, much faster in the frame loop than :meth:`SignalCodec.extract`'s byte loop): a
    field beyond byte 7 (CAN FD) leaves the protocol to the careful path.
    """

    __slots__ = ("options", "msg", "period", "sig", "sig_f", "n_float", "layout", "counts",
                 "out_f", "out_i")

    def __init__(self, p: Protocol) -> None:
        self.options = (p.strict_range, p.check_crc, p.check_counter)
        K = len(p.messages)
        roles = [r for m in p.messages for r in m.roles]
        counters = [m.counter for m in p.messages if m.counter is not None]
        self.msg = np.full((K, _M_COLS), -1, np.int64)
        self.period = np.zeros(K, np.float64)
        self.sig = np.zeros((len(roles) + len(counters), _S_COLS), np.int64)
        self.sig_f = np.zeros((len(roles), _F_COLS), np.float64)
        layout = []
        s, q, row = 0, len(roles), 0
        for k, m in enumerate(p.messages):
            mk = self.msg[k]
            mk[_M_ID], mk[_M_EXT], mk[_M_LEN] = m.frame_id, m.is_extended, m.length
            mk[_M_CRC], mk[_M_CHECK] = m.crc is not None and p.check_crc, p.check_counter
            if m.counter is not None:
                mk[_M_MOD], mk[_M_WINDOW], self.period[k] = _counter_params(m)
                mk[_M_COUNTER] = q
                self._locate(q, m.counter)
                q += 1
            mk[_M_SIG0], mk[_M_SIG1], mk[_M_TROW] = s, s + len(m.roles), row
            for r in m.roles:
                row += 1
                self._locate(s, r.codec)
                self._scaling(s, r, p.strict_range)
                self.sig[s, _S_ROW] = row
                s += 1
            row += 1
            layout.append((m.name, int(mk[_M_TROW]), tuple(r.role for r in m.roles),
                           m.counter_modulo))
        self.n_float = row
        self.layout: tuple[tuple[str, int, tuple[str, ...], int | None], ...] = tuple(layout)
        self.counts = np.zeros(2 * K + 1, np.int64)
        self.out_f = np.empty((self.n_float, 0), np.float64)
        self.out_i = np.empty((2 * K, 0), np.int64)

    def outputs(self, n: int) -> tuple[F64, I64]:
        """The kernel's float and integer outputs for ``n`` frames: kept between blocks and
        grown as needed (fresh large arrays on every block cost page faults)."""
        if self.out_f.shape[1] < n:
            cols = max(n, self.out_f.shape[1] * 3 // 2)
            self.out_f = np.empty((self.n_float, cols), np.float64)
            self.out_i = np.empty((self.out_i.shape[0], cols), np.int64)
        return self.out_f, self.out_i

    def _locate(self, s: int, c: SignalCodec) -> None:
        """Row ``s`` of ``sig``: where the field of ``c`` lies in the payload words."""
        if max(c.byte_index) > 7:
            raise _NoFastPath(c.qualname)
        row = self.sig[s]
        row[_S_SIGNED], row[_S_FLOAT], row[_S_LEN] = c.is_signed, c.is_float, c.length
        # raw bit b is bit (b + shift) % 8 of byte byte_index[(b + shift) // 8] (SignalCodec):
        # ascending bytes (little endian) or descending (big endian) from byte_index[0]
        row[_S_BE] = c.byte_order != "little_endian"
        row[_S_POS] = 8 * (7 - c.byte_index[0] if row[_S_BE] else c.byte_index[0]) + c.shift

    def _scaling(self, s: int, r: RoleInfo, strict_range: bool) -> None:
        """Rows ``s`` of ``sig`` and ``sig_f``: how role ``r`` scales, its range check."""
        c = r.codec
        scaling = c.scaling()
        if scaling is None:
            raise _NoFastPath(c.qualname)
        mode, scale, offset = scaling
        self.sig[s, _S_MODE] = mode
        if mode == PHYS_INT:
            self.sig[s, _S_SCALE], self.sig[s, _S_OFFSET] = scale, offset
        else:
            self.sig_f[s, _F_SCALE], self.sig_f[s, _F_OFFSET] = scale, offset
        # the bounds SignalCodec.out_of_range compares with
        lo, hi = (c.minimum, c.maximum) if strict_range else (None, None)
        self.sig_f[s, _F_LO] = lo - c.tol if lo is not None else -np.inf
        self.sig_f[s, _F_HI] = hi + c.tol if hi is not None else np.inf
        self.sig_f[s, _F_SI] = r.si_scale

    @staticmethod
    def build(p: Protocol) -> _FastPlan | None:
        """The plan, or None when a mapped signal is beyond the kernel (a field beyond
        payload byte 7, a scaling :meth:`SignalCodec.scaling` declines)."""
        try:
            return _FastPlan(p)
        except _NoFastPath:
            return None


def _fast_kernel(t: F64, arbitration_id: npt.NDArray[np.uint32],
                 is_extended: npt.NDArray[np.bool_], is_remote: npt.NDArray[np.bool_],
                 is_error: npt.NDArray[np.bool_], dlc: U8, data: U8, msg: I64, period: F64,
                 sig: I64, sig_f: F64, powers: U8, state: I64, state_t: F64, base: int,
                 out_f: F64, out_i: I64, counts: I64) -> int:
    """Decode the frames of a block in one pass, up to the first that is not well-formed.

    Frames in stream order; a frame belongs to the message (row of ``msg``) with its ID
    and format. Per frame of a message: not remote, DLC = the message length, CRC
    (:func:`crc_vector`), alive counter in sequence (:func:`_counter_kernel`), each role's
    physical value ``raw * scale + offset`` (as :meth:`SignalCodec.physical` computes it,
    see :meth:`SignalCodec.scaling`) finite and within [lo, hi]; then the time, stream
    index ``base + i``, counter (or running sequence number) and SI values ``physical *
    si_scale`` go to the outputs (see :class:`_FastPlan`). ``state`` = per message the
    counter state of :func:`_counter_kernel`, then the sequence number (``_ST_COLS``
    columns), ``state_t`` = [time of the last accepted frame].

    Stops at the first error frame or frame of a mapped message that fails a check, and
    returns the number of frames decoded: outputs, counts and state are those of the
    frames before it, and the caller decodes the rest the careful way.
    """
    c = np.ascontiguousarray  # a no-op for the arrays of a FrameBlock
    d = c(data, np.uint8)
    return int(_can.decode_fast(c(t, np.float64), c(arbitration_id, np.uint32),
                                c(is_extended, np.bool_), c(is_remote, np.bool_),
                                c(is_error, np.bool_), c(dlc, np.uint8), d, d.shape[1], msg,
                                period, sig, sig_f, powers, state, state_t, int(base), out_f,
                                out_i, counts))


class Decoder:
    """Stateful strict decoder of the mapped feedback messages (``Decoder(protocol)``).

    Running totals: ``rejected`` (:class:`RejectCounts`), ``lost`` (message -> frames
    missing by counter), ``accepted`` (message -> frames passed on), ``foreign``
    (frames of other IDs) and ``frames`` (all frames seen). Decoding is chunk-invariant:
    the alive-counter state is carried from block to block.
    """

    def __init__(self, protocol: Protocol) -> None:
        self.protocol = protocol
        self.rejected = RejectCounts()
        self.lost: dict[str, int] = {m.name: 0 for m in protocol.messages}
        self.accepted: dict[str, int] = {m.name: 0 for m in protocol.messages}
        self.foreign = 0
        self.frames = 0
        # per message: [last counter, run, last counter of the run, skipped, trusted] (see
        # _counter_kernel), then the running sequence number of a message without counter;
        # time of the last accepted frame. The careful path works on views of the rows.
        K = len(protocol.messages)
        self._counters = np.tile(np.array([-1, 0, -1, 0, 1, 0], np.int64), (K, 1))
        self._counters_t = np.zeros(K, np.float64)
        self._state = {m.name: (self._counters[k, :_ST_COUNTER_COLS],
                                self._counters_t[k:k + 1])
                       for k, m in enumerate(protocol.messages)}
        self._seq = {m.name: self._counters[k, _ST_COUNTER_COLS:]
                     for k, m in enumerate(protocol.messages)}
        self._plan = _FastPlan.build(protocol)

    def decode(self, block: FrameBlock) -> DecodedFrames:
        """Decode one block; rejected frames are counted and dropped, never passed on.

        The frames up to the first that is not well-formed (all of them, commonly) are
        decoded in one compiled pass (:func:`_fast_kernel`); the rest the careful way,
        check by check, which also names each rejection. Decoding being chunk-invariant,
        the result is that of the careful way on the whole block.
        """
        p = self.protocol
        n = len(block)
        base = self.frames
        self.frames += n
        plan = self._plan
        if plan is not None and plan.options != (p.strict_range, p.check_crc, p.check_counter):
            plan = self._plan = _FastPlan.build(p)
        if plan is None:
            return self._decode_careful(block, base)
        fast, done = self._decode_fast(plan, block, base)
        if done == n:
            return fast
        rest = self._decode_careful(block.take(slice(done, None)) if done else block,
                                    base + done)
        return _joined(fast, rest) if done else rest

    def _decode_careful(self, block: FrameBlock, base: int) -> DecodedFrames:
        """Decode a block check by check (the frames numbered from ``base`` in the stream)."""
        p = self.protocol
        n = len(block)
        rej = RejectCounts()
        err = block.is_error
        n_err = int(err.sum())
        if n_err:
            k = int(np.flatnonzero(err)[0])
            rej.add("error_frame", "*", n_err, f"error frame at t={block.t[k]:.6f} s", base + k)
        mine = np.zeros(n, np.bool_)
        out: dict[str, MessageFrames] = {}
        lost_block: dict[str, int] = {}
        for m in p.messages:
            # rows of this message: its ID and format, not an error frame (mine |= them)
            rows = _select_rows(block.arbitration_id, block.is_extended, err, int(m.frame_id),
                                bool(m.is_extended), mine)
            frames, lost = self._decode_message(m, block, rows, base, rej)
            out[m.name] = frames
            lost_block[m.name] = lost
            self.lost[m.name] += lost
            self.accepted[m.name] += len(frames)
        foreign = int(n - n_err - mine.sum())
        self.foreign += foreign
        self.rejected.merge(rej)
        return DecodedFrames(out, rej, lost_block, foreign)

    def _decode_fast(self, plan: _FastPlan, block: FrameBlock,
                     base: int) -> tuple[DecodedFrames, int]:
        """:func:`_fast_kernel` on the block: the decoded frames (counted in the running
        totals) and how many of the block's frames they cover."""
        out_f, out_i = plan.outputs(len(block))
        done = _fast_kernel(block.t, block.arbitration_id, block.is_extended, block.is_remote,
                            block.is_error, block.dlc, block.data, plan.msg, plan.period,
                            plan.sig, plan.sig_f, CRC8_POWERS, self._counters, self._counters_t,
                            base, out_f, out_i, plan.counts)
        counts = plan.counts.tolist()
        K = len(plan.layout)
        out: dict[str, MessageFrames] = {}
        lost: dict[str, int] = {}
        for k, (name, t_row, roles, modulo) in enumerate(plan.layout):
            c = counts[k]
            f = out_f[t_row:t_row + 1 + len(roles), :c].copy()  # times, then the roles
            i = out_i[2 * k:2 * k + 2, :c].copy()  # stream indices, counters
            out[name] = MessageFrames(name, f[0], i[0], i[1],
                                      {role: f[1 + j] for j, role in enumerate(roles)}, modulo)
            lost[name] = counts[K + k]
            self.lost[name] += counts[K + k]
            self.accepted[name] += c
        foreign = counts[2 * K]
        self.foreign += foreign
        return DecodedFrames(out, RejectCounts(), lost, foreign), done

    def _decode_message(self, m: MessageCodec, block: FrameBlock, rows: npt.NDArray[np.intp],
                        base: int, rej: RejectCounts) -> tuple[MessageFrames, int]:
        p = self.protocol
        t = block.t[rows]
        reason = np.zeros(len(rows), np.int8)

        def reject(mask: npt.NDArray[np.bool_], name: str, example: Any) -> None:
            mask = mask & (reason == 0)
            if mask.any():
                k = int(np.flatnonzero(mask)[0])
                reason[mask] = _R[name]
                key = base + int(rows[k])
                want = self.rejected.wants_example(name, key) and rej.wants_example(name, key)
                rej.add(name, m.name, int(mask.sum()), example(k) if want else None, key)

        n_rows = len(rows)
        crc_on = m.crc is not None and p.check_crc
        if block.data.shape[1] >= m.length:
            # one compiled pass: payload bytes of every row, and the first of remote /
            # length / CRC that fails (flags 1, 2, 4; 0: passed)
            gathered = np.empty((n_rows, m.length), np.uint8)
            flags = np.empty(n_rows, np.uint8)
            n_bad = _gather_check(block.data, rows, m.length, block.is_remote, block.dlc,
                                  crc_on, int(m.frame_id), CRC8_POWERS, gathered, flags)
        else:  # a block narrower than the message: the checks below, one by one
            gathered, flags, n_bad = None, None, n_rows
        # payload bytes of the rows still accepted; the rows only ever shrink, so the
        # same count means the same rows and the gathered bytes can be reused
        cache: list[Any] = [None, None]
        if n_bad == 0 and gathered is not None:
            cache = [np.arange(n_rows), gathered]

        def accepted() -> tuple[npt.NDArray[np.intp], U8]:
            ok = np.flatnonzero(reason == 0)
            if cache[0] is None or len(cache[0]) != len(ok):
                cache[0] = ok
                if not len(ok):
                    cache[1] = np.zeros((0, m.length), np.uint8)
                elif gathered is not None:
                    cache[1] = gathered[ok]
                else:
                    cache[1] = block.data[rows[ok], :m.length]
            return cache[0], cache[1]

        if n_bad:
            reject(block.is_remote[rows], "remote",
                   lambda k: f"{m.name}: remote frame (t={t[k]:.6f} s)")
            dlc = block.dlc[rows]
            reject(dlc != m.length, "length",
                   lambda k: f"{m.name}: {dlc[k]} bytes, expected {m.length} (t={t[k]:.6f} s)")
            ok, data = accepted()
            if crc_on and len(ok):
                if flags is not None:
                    bad = flags == 4
                else:
                    bad = np.zeros(len(rows), np.bool_)
                    bad[ok] = crc_vector(m.frame_id, data, m.length) != data[:, 0]

                def crc_example(k: int) -> str:
                    good = int(crc_vector(m.frame_id, block.data[rows[k:k + 1], :m.length],
                                           m.length)[0])
                    return (f"{m.name}: CRC 0x{block.data[rows[k], 0]:02X}, computed "
                            f"0x{good:02X} (t={t[k]:.6f} s)")

                reject(bad, "crc", crc_example)
        lost_total = 0
        counter_all = np.zeros(len(rows), np.int64)
        modulo = m.counter_modulo
        if m.counter is not None:
            ok, data = accepted()
            if len(ok):
                counter_all[ok] = m.counter.raw(data)
            # frames rejected for their length or CRC were received: not lost
            skip = (reason == _R["length"]) | (reason == _R["crc"])
            if p.check_counter and (len(ok) or skip.any()):
                state, state_t = self._state[m.name]
                before = int(state[0])
                # the accepted rows and those, in stream order (the accepted ones alone
                # when none was rejected so)
                sel = np.flatnonzero((reason == 0) | skip)
                status, lost = _counter_kernel(counter_all[sel], t[sel], *_counter_params(m),
                                               state, state_t, skip[sel])
                status = status[~skip[sel]]
                lost_total = int(lost.sum())

                def previous(k: int) -> int:
                    j = np.flatnonzero((ok < k) & (status == _STATUS_OK))
                    return int(counter_all[ok[j[-1]]]) if len(j) else before

                for code, name in ((_STATUS_REPEATED, "repeated"), (_STATUS_STALE, "stale"),
                                   (_STATUS_SEQUENCE, "sequence")):
                    if not status.any():
                        break
                    bad = np.zeros(len(rows), np.bool_)
                    bad[ok] = status == code
                    reject(bad, name, lambda k, name=name: (
                        f"{m.name}: counter {counter_all[k]} {name} after counter "
                        f"{previous(k)} (t={t[k]:.6f} s)"))
        # values of the mapped roles
        ok, data = accepted()
        phys: dict[str, F64] = {}
        for r in m.roles:
            phys[r.role] = r.codec.physical(data)
        for r in m.roles:
            v = phys[r.role]
            if r.codec.is_float:
                nan = ~np.isfinite(v)
                if not nan.any():
                    continue
                bad = np.zeros(len(rows), np.bool_)
                bad[ok] = nan
                reject(bad, "nan", lambda k, r=r: (
                    f"{r.codec.qualname} = {_phys_at(r.codec, block, rows, k, m.length)} "
                    f"{r.codec.unit} (t={t[k]:.6f} s)"))
        if p.strict_range:
            for r in m.roles:
                oor = r.codec.out_of_range(phys[r.role])
                if not oor.any():
                    continue
                bad = np.zeros(len(rows), np.bool_)
                bad[ok] = oor
                c = r.codec
                lo = format_value(c.minimum) if c.minimum is not None else "-inf"
                hi = format_value(c.maximum) if c.maximum is not None else "inf"
                reject(bad, "range", lambda k, c=c, lo=lo, hi=hi: (
                    f"{c.qualname} = {format_value(_phys_at(c, block, rows, k, m.length))} "
                    f"{c.unit} outside [{lo}, {hi}] (t={t[k]:.6f} s)"))
        keep_local = reason[ok] == 0
        if len(ok) == n_rows and keep_local.all():  # every row accepted
            keep = ok
            values = {r.role: phys[r.role] * r.si_scale for r in m.roles}
            t_keep = t
            counter = counter_all if modulo is not None else None
        else:
            keep = ok[keep_local]
            values = {r.role: phys[r.role][keep_local] * r.si_scale for r in m.roles}
            t_keep = t[keep]
            counter = counter_all[keep] if modulo is not None else None
        if counter is None:
            seq = self._seq[m.name]
            s0 = int(seq[0])
            counter = np.arange(s0, s0 + len(keep), dtype=np.int64)
            seq[0] = s0 + len(keep)
        index = (rows if len(keep) == n_rows else rows[keep]).astype(np.int64, copy=False) + base
        frames = MessageFrames(m.name, t_keep, index, counter, values, modulo)
        return frames, lost_total


def _joined(a: DecodedFrames, b: DecodedFrames) -> DecodedFrames:
    """Two consecutive parts of a block decoded as one; ``a`` has no rejections."""
    cat = np.concatenate
    out = {}
    for name, x in a.messages.items():
        y = b.messages[name]
        out[name] = MessageFrames(name, cat([x.t, y.t]), cat([x.index, y.index]),
                                  cat([x.counter, y.counter]),
                                  {r: cat([v, y.values[r]]) for r, v in x.values.items()},
                                  x.counter_modulo)
    return DecodedFrames(out, b.rejected, {k: v + b.lost[k] for k, v in a.lost.items()},
                         a.foreign + b.foreign)


def _phys_at(c: SignalCodec, block: FrameBlock, rows: npt.NDArray[np.intp], k: int,
             length: int) -> float:
    return float(c.physical(block.data[rows[k:k + 1], :length])[0])


# ---------------------------------------------------------------------------
