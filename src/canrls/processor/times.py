"""When a frame's receive time is a time: one judgment for the log readers and the live path.

A time at all (:func:`canrls.core.checks.is_time`: finite, within
:data:`~canrls.core.checks.MAX_TIMESTAMP`), and in line with the stream
(:class:`TimeJudge`: a lone outlier more than
:data:`~canrls.processor.pairing.FORWARD_STEP` off, whose next frames come back, is
rejected as ``time``; a departure that stays is a clock step, left to the pairer). The
judgment carries its state from block to block, so any split of the stream gives the
same frames (docs/protocol.md, "Clock faults and reordering").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from canrls.can.frameblock import FrameBlock
from canrls.core.checks import describe_time, not_times

__all__ = ["SPIKE_FRAMES", "STEP_S", "TimeJudge", "TimeRejects"]

F64 = npt.NDArray[np.float64]

#: Seconds a frame may lie before or after the last frame accepted and still be in line
#: with the stream (:data:`canrls.processor.pairing.FORWARD_STEP`, the pairer's clock-step
#: bound; a copy, so that this module imports nothing of the pairer's C kernel).
STEP_S = 1.0

#: Most frames a departure from the time base may hold and still be rejected as an
#: outlier when the stream comes back (a receiver may stamp a whole packet of frames
#: with one bad time); a longer departure is a clock step.
SPIKE_FRAMES = 16


@dataclass
class TimeRejects:
    """Frames a :class:`TimeJudge` rejected (running totals) and the first example."""

    #: frames whose timestamp is not a time (:func:`is_time`)
    invalid: int = 0
    #: lone outliers: frames that left the time base and that the stream came back from
    outliers: int = 0
    #: the first rejected frame, in words (None: none yet)
    example: str | None = None

    @property
    def total(self) -> int:
        return self.invalid + self.outliers


class TimeJudge:
    """The stream's receive times judged frame by frame (docs/protocol.md).

    :meth:`push` returns the frames accepted so far, in stream order, and keeps a
    departure from the time base until the frames after it decide it; :meth:`flush`
    passes a departure still held on (nothing came back from it: a clock step).
    :meth:`rejected` returns the rows rejected by the last call, for counting.
    """

    def __init__(self, step: float = STEP_S, spike_frames: int = SPIKE_FRAMES) -> None:
        self.step = float(step)
        self.spike_frames = int(spike_frames)
        #: time of the last frame accepted (None: none yet)
        self.last: float | None = None
        self._held: list[FrameBlock] = []
        self._held_n = 0
        self._held_last = 0.0
        self.counts = TimeRejects()
        self._rejected: list[FrameBlock] = []

    @property
    def held(self) -> int:
        """Frames held: a departure from the time base still undecided."""
        return self._held_n

    def _in_line(self, t: float, ref: float) -> bool:
        return ref - self.step <= t <= ref + self.step

    def push(self, block: FrameBlock) -> FrameBlock:
        """The frames of ``block`` (after those held from before) that are accepted."""
        self._rejected = []
        if not len(block):
            return block
        t = block.t
        bad = not_times(t)
        if bad.any():
            self._reject(block.take(bad), invalid=True)
            block = block.take(~bad)
            t = block.t
            if not len(block):
                return block
        d = np.diff(t)
        # fast path: nothing held, every frame in line with the one before it
        if not self._held and (self.last is None or self._in_line(float(t[0]), self.last)) \
                and bool(np.all(np.abs(d) <= self.step)):
            self.last = float(t[-1])
            return block
        # runs of frames each in line with the one before; judge each run's first frame
        cuts = np.flatnonzero(~(np.abs(d) <= self.step)) + 1
        starts = np.concatenate([[0], cuts]).tolist()
        ends = np.concatenate([cuts, [len(t)]]).tolist()
        out: list[FrameBlock] = []
        for a, b in zip(starts, ends, strict=True):
            run = block.take(slice(a, b))
            first, end = float(t[a]), float(t[b - 1])
            if self._held:
                if self.last is not None and self._in_line(first, self.last):
                    # back on the time base: the departure held was an outlier
                    self._reject(FrameBlock.concat(self._held), invalid=False)
                    self._drop_held()
                elif self._in_line(first, self._held_last):
                    self._hold(run, end)
                    if self._held_n > self.spike_frames:
                        out.extend(self._release())
                    continue
                else:
                    out.extend(self._release())
            if self.last is None or self._in_line(first, self.last):
                out.append(run)
                self.last = end
            else:
                self._hold(run, end)
                if self._held_n > self.spike_frames:
                    out.extend(self._release())
        if not out:
            return block.take(slice(0, 0))
        return out[0] if len(out) == 1 else FrameBlock.concat(out)

    def flush(self) -> FrameBlock:
        """End of stream: a departure still held is passed on (a clock step)."""
        self._rejected = []
        parts = self._release()
        return FrameBlock.concat(parts) if parts else FrameBlock.empty()

    def rejected(self) -> FrameBlock | None:
        """The frames the last :meth:`push` or :meth:`flush` rejected (None: none)."""
        if not self._rejected:
            return None
        return FrameBlock.concat(self._rejected)

    def _hold(self, run: FrameBlock, end: float) -> None:
        self._held.append(run)
        self._held_n += len(run)
        self._held_last = end

    def _drop_held(self) -> None:
        self._held = []
        self._held_n = 0

    def _release(self) -> list[FrameBlock]:
        """The frames held, accepted: a clock step (the time base moves with them)."""
        parts = self._held
        if parts:
            self.last = self._held_last
        self._drop_held()
        return parts

    def _reject(self, frames: FrameBlock, invalid: bool) -> None:
        self._rejected.append(frames)
        if invalid:
            self.counts.invalid += len(frames)
        else:
            self.counts.outliers += len(frames)
        if self.counts.example is None:
            t = float(frames.t[0])
            before = "" if self.last is None else f", t={self.last:.6f} s"
            why = describe_time(t) if invalid else (
                f"timestamp {t!r} s is out of line with the frames around it (more than "
                f"{self.step:g} s from the frame before{before}, and the frames after it "
                f"came back)")
            self.counts.example = f"frame 0x{int(frames.arbitration_id[0]):X}: {why}"
