"""Pairing: from decoded feedback frames to samples, one per control period.

:class:`Pairer` groups the frames of one period (timestamps within ``tolerance``, equal
alive counters) and emits a :class:`~canrls.core.samples.Signals` row when every mapped
message of that period is there; an incomplete period is dropped and counted, never
filled from another. Time stays monotonic across clock steps (:data:`CLOCK_KINDS`), and
any split of the stream gives the same samples. The rules: docs/protocol.md, "Pairing".
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from canrls import _can
from canrls.can.decoder import DecodedFrames
from canrls.can.protocol import Protocol
from canrls.core.errors import ConfigError
from canrls.core.samples import ROLES, Signals

__all__ = ["Pairer", "PairingCounts", "PAIRING_KINDS", "CLOCK_KINDS", "STEP_PERIODS",
           "FORWARD_STEP"]

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

#: What :class:`PairingCounts` counts per message (frames).
PAIRING_KINDS: tuple[str, ...] = ("unpaired", "lost", "duplicated", "reordered", "late")
_UNPAIRED, _LOST, _DUP, _REORD, _LATE = range(5)

#: Clock faults a :class:`Pairer` counts (events, not frames; docs/protocol.md, "Pairing").
CLOCK_KINDS: tuple[str, ...] = ("step_back", "step_forward", "gap")

#: Periods a frame must lie before the newest to be a clock step back (not late).
STEP_PERIODS = 16

#: Seconds a frame must lie after the newest to be a clock step forward (not a gap).
FORWARD_STEP = 1.0

_CAPACITY = 64  # open periods kept at most (the oldest is forced out beyond that)


@dataclass
class PairingCounts:
    """Counts of a :class:`Pairer` (running totals).

    ``samples`` emitted; frames ``unpaired`` (dropped: their period never completed),
    ``lost`` (frames the pairer never saw: missing partners and whole missing
    periods -- lost on the bus or rejected by the decoder), ``duplicated`` and
    ``late`` (dropped), ``reordered`` (arrived after a later period's frame, still
    paired). ``per_message[name][kind]`` splits the frame counts by message.
    """

    samples: int = 0
    per_message: dict[str, dict[str, int]] = field(default_factory=dict)
    #: clock faults ``{kind: events}`` (kinds of :data:`CLOCK_KINDS`)
    clock: dict[str, int] = field(default_factory=lambda: dict.fromkeys(CLOCK_KINDS, 0))

    def _total(self, kind: str) -> int:
        return sum(m[kind] for m in self.per_message.values())

    @property
    def unpaired(self) -> int:
        return self._total("unpaired")

    @property
    def lost(self) -> int:
        return self._total("lost")

    @property
    def duplicated(self) -> int:
        return self._total("duplicated")

    @property
    def reordered(self) -> int:
        return self._total("reordered")

    @property
    def late(self) -> int:
        return self._total("late")

    def as_dict(self) -> dict[str, int]:
        """``{"samples": .., "unpaired": .., "lost": .., ..., "step_back": .., ...}``
        (totals: frames of :data:`PAIRING_KINDS`, events of :data:`CLOCK_KINDS`)."""
        return {"samples": self.samples, **{k: self._total(k) for k in PAIRING_KINDS},
                **{k: int(self.clock.get(k, 0)) for k in CLOCK_KINDS}}

    def summary(self) -> str:
        return ", ".join(f"{k} {v}" for k, v in self.as_dict().items())


def _push_kernel(index: tuple[I64, ...], t: tuple[F64, ...], cnt: tuple[I64, ...],
                 vals: tuple[F64, ...], use_counters: bool, role_msg: I64, times: F64,
                 flush: bool, gf: F64, gi: I64, sf: F64, si: I64, counts: I64, clock: I64,
                 iwork: I64, fwork: F64, vwork: F64) -> F64:
    """One push (``push`` in ``src/canrls/c/host/can.c``): the frames of each message
    (``index``, ``t``, ``cnt``: one array per message; ``vals``: one array per role, of
    the role's message) merged into stream order (a stable sort by ``index`` when a
    message's frames are out of order), then processed one at a time (``times`` =
    [tolerance, wait, period, back, step, gap]: the bounds of docs/protocol.md, "Pairing").
    Counters are ignored (-1) unless ``use_counters``.
    ``iwork`` (4, C), ``fwork`` (3, C) and ``vwork`` (3, C, R) are scratch space for C >=
    frames + open-period capacity. Returns the completed samples as rows [t, role
    values...].

    State: the open periods are the slots 0 .. gi[0, 0]-1 (kept compact): gi[1 + g] =
    [unused, counter (-1: none), mask of messages present]; gf[g] = [t_min, t_max,
    values of the roles...]. sf = [newest frame time, t_min and t_max of the last
    finalised period, whether there is one (0/1), offset of the time base]; si = per
    message: -2 if absent from that period, else its counter (-1: none).
    counts[kind, message] (kinds in the order of :data:`PAIRING_KINDS`); clock[kind]
    (:data:`CLOCK_KINDS`).
    """
    c = np.ascontiguousarray
    n_out = _can.push(tuple([c(a, np.int64) for a in index]),
                      tuple([c(a, np.float64) for a in t]),
                      tuple([c(a, np.int64) for a in cnt]),
                      tuple([c(a, np.float64) for a in vals]), use_counters, role_msg, times,
                      flush, gf, gi, sf, si, counts, clock, iwork, fwork, vwork)
    out = np.empty((1 + len(role_msg), n_out), np.float64)
    out[0] = fwork[2, :n_out]
    out[1:] = vwork[2, :n_out].T
    return out


class Pairer:
    """Pair decoded feedback frames into samples (the rules: docs/protocol.md, "Pairing").

    Parameters
    ----------
    protocol : the :class:`~canrls.can.protocol.Protocol` whose messages are paired.
    period : control period [s]; default: the mapped messages' ``GenMsgCycleTime``.
    tolerance : largest time difference [s] between frames of one period
        (default ``period / 2``).
    hold : periods an incomplete period waits for a late partner (default 1).
    match_counters : require equal alive counters within a period when the messages
        carry counters of the same range (default True).
    back : a frame this far [s] before the newest is a clock step back (default
        :data:`STEP_PERIODS` periods, at least the wait of ``hold``).
    step : a frame this far [s] after the newest is a clock step forward (default
        :data:`FORWARD_STEP`, at least the gap bound).

    Raises
    ------
    ConfigError
        No period is configured and the DBC gives no ``GenMsgCycleTime``.
    """

    def __init__(self, protocol: Protocol, *, period: float | None = None,
                 tolerance: float | None = None, hold: int = 1,
                 match_counters: bool = True, back: float | None = None,
                 step: float | None = None) -> None:
        self.protocol = protocol
        per = period if period is not None else protocol.period
        if per is None or not np.isfinite(per) or per <= 0:
            raise ConfigError(
                f"pairing needs the control period: DBC {protocol.dbc_path} gives no "
                f"GenMsgCycleTime for {', '.join(m.name for m in protocol.messages)}; "
                f"state the period (--period, [can] period) or let the front end measure it "
                f"(canrls.processor.FrameProcessor)")
        self.period = float(per)
        self.tolerance = float(tolerance) if tolerance is not None else self.period / 2
        if not (0 < self.tolerance < self.period):
            raise ConfigError(f"pairing tolerance must lie in (0, period={self.period}), "
                              f"got {self.tolerance}")
        if hold < 0:
            raise ConfigError(f"pairing hold must be >= 0 periods, got {hold}")
        self.hold = int(hold)
        self.messages: tuple[str, ...] = tuple(m.name for m in protocol.messages)
        self.roles: tuple[str, ...] = tuple(r for r in ROLES if protocol.has(r))
        self._msg_index = {name: k for k, name in enumerate(self.messages)}
        # each role with the position of its message; row of each of ROLES in the output
        self._role_parts = tuple((r, self._msg_index[protocol.roles[r].message])
                                 for r in self.roles)
        self._role_msg = np.array([k for _, k in self._role_parts], np.int64)
        self._rows = tuple(1 + self.roles.index(r) if r in self.roles else None for r in ROLES)
        moduli = {m.counter_modulo for m in protocol.messages}
        self.match_counters = bool(match_counters) and None not in moduli and len(moduli) == 1
        K, R = len(self.messages), len(self.roles)
        self._gf = np.zeros((_CAPACITY, 2 + R), np.float64)
        self._gi = np.zeros((_CAPACITY + 1, 3), np.int64)
        self._sf = np.array([-np.inf, np.nan, np.nan, 0.0, 0.0])
        self._clock = np.zeros(len(CLOCK_KINDS), np.int64)
        self._si = np.full(K, -2, np.int64)
        self._counts = np.zeros((len(PAIRING_KINDS), K), np.int64)
        self._samples = 0
        wait = self.tolerance + self.hold * self.period
        gap = wait + self.period
        self.back = float(back) if back is not None else max(wait, STEP_PERIODS * self.period)
        self.step = float(step) if step is not None else max(gap, FORWARD_STEP)
        if not (np.isfinite(self.back) and self.back >= wait):
            raise ConfigError(f"pairing: the clock-step bound back={self.back!r} s must be "
                              f"at least the wait {wait} s (tolerance + hold periods)")
        if not (np.isfinite(self.step) and self.step >= gap):
            raise ConfigError(f"pairing: the clock-step bound step={self.step!r} s must be "
                              f"at least the gap bound {gap} s")
        self._times = np.array([self.tolerance, wait, self.period, self.back, self.step, gap])
        # the input of a flush: no frames
        none_i, none_f = np.zeros(0, np.int64), np.zeros(0, np.float64)
        self._no_frames = ((none_i,) * K, (none_f,) * K, (none_i,) * K, (none_f,) * R)
        self._iwork = np.empty((4, 0), np.int64)
        self._work(0)

    @property
    def counts(self) -> PairingCounts:
        """Running totals (a snapshot)."""
        return PairingCounts(self._samples, {
            name: {kind: int(self._counts[j, k]) for j, kind in enumerate(PAIRING_KINDS)}
            for k, name in enumerate(self.messages)},
            {kind: int(v) for kind, v in zip(CLOCK_KINDS, self._clock.tolist(), strict=True)})

    @property
    def offset(self) -> float:
        """The offset [s] of the time base: sample time = timestamp + offset (0 until a
        clock step back re-anchors it)."""
        return float(self._sf[4])

    @property
    def pending(self) -> int:
        """Periods still open (waiting for a partner or behind an older open period)."""
        return int(self._gi[0, 0])

    def push(self, decoded: DecodedFrames) -> Signals:
        """Add one decoded block; return the samples completed by it (possibly none)."""
        return self._run(decoded, flush=False)

    def flush(self) -> Signals:
        """End of stream: emit the complete periods still waiting, drop the incomplete ones."""
        return self._run(None, flush=True)

    def _work(self, n: int) -> None:
        """Scratch space of :func:`_push_kernel` for ``n`` frames, kept between calls and
        grown as needed: large fresh arrays on every block cost page faults."""
        cols = max(n + _CAPACITY, self._iwork.shape[1] * 3 // 2)
        self._iwork = np.empty((4, cols), np.int64)
        self._fwork = np.empty((3, cols), np.float64)
        self._vwork = np.empty((3, cols, len(self.roles)), np.float64)

    def _run(self, decoded: DecodedFrames | None, flush: bool) -> Signals:
        if decoded is None:
            index, t, cnt, vals = self._no_frames
        else:
            # one array per message (per role for the values): the kernel merges them
            parts = [decoded.messages[name] for name in self.messages]
            index = tuple([p.index for p in parts])
            t = tuple([p.t for p in parts])
            cnt = tuple([p.counter for p in parts])
            vals = tuple([parts[k].values[role] for role, k in self._role_parts])
        n = sum([len(a) for a in index])
        if n + _CAPACITY > self._iwork.shape[1]:
            self._work(n)
        out = _push_kernel(index, t, cnt, vals, self.match_counters, self._role_msg, self._times,
                           flush, self._gf, self._gi, self._sf, self._si, self._counts,
                           self._clock, self._iwork, self._fwork, self._vwork)
        self._samples += out.shape[1]
        c, s, p, v, q = self._rows
        return Signals(out[0], None if c is None else out[c], out[s],
                       None if p is None else out[p], None if v is None else out[v],
                       None if q is None else out[q])
