"""Put frames reordered on the way back in their order, by their alive counters.

A gateway, a driver queue or a merged log can swap a frame with its neighbour of the
same ID: the receive times keep their order, the contents do not. :class:`Reorderer`
runs before the strict decoder and, within :data:`REORDER_WINDOW` frames of a message
that carries a counter, moves the contents back to their places, the timestamps staying
where they are; a real loss, repeats and stale counters are left to the decoder. The
rule and what it is worth: docs/protocol.md, "Clock faults and reordering".
"""

from __future__ import annotations

import heapq
from collections.abc import Sequence
from typing import Any

import numpy as np

from canrls.can.frameblock import FrameBlock

__all__ = ["REORDER_WINDOW", "Reorderer"]

#: Frames of one message within which a frame is put back in its place.
REORDER_WINDOW = 3

_CONTENT = ("is_extended", "is_remote", "is_error", "dlc", "data")


class Reorderer:
    """Reorder the frames of counter-carrying messages (docs/protocol.md).

    Parameters
    ----------
    messages : the mapped messages (:class:`~canrls.can.protocol.MessageCodec`); those
        without a counter are passed on as they come.
    window : :data:`REORDER_WINDOW` (0: pass everything on as it comes).
    """

    def __init__(self, messages: Sequence[Any], window: int = REORDER_WINDOW) -> None:
        self.window = int(window)
        self._msgs = [m for m in messages if getattr(m, "counter", None) is not None]
        self._last: dict[str, int | None] = {m.name: None for m in self._msgs}
        self._held: FrameBlock | None = None
        #: frames moved up to their place (a neighbour swap counts one; running total)
        self.moved = 0

    @property
    def held(self) -> int:
        """Frames held back for the next block."""
        return 0 if self._held is None else len(self._held)

    def push(self, block: FrameBlock) -> FrameBlock:
        """The block (after the frames held from the last one) in counter order, without
        the frames held for the next block."""
        if self._held is not None:
            block = FrameBlock.concat([self._held, block]) if len(block) else self._held
            self._held = None
        if not self._msgs or self.window <= 0 or not len(block):
            return block
        hold = np.zeros(len(block), np.bool_)
        copied = False
        for m in self._msgs:
            rows = np.flatnonzero((block.arbitration_id == m.frame_id)
                                  & (block.is_extended == m.is_extended)
                                  & ~block.is_error & ~block.is_remote
                                  & (block.dlc == m.length))
            if not len(rows):
                continue
            codec = m.counter
            mod = 1 << codec.length
            c = codec.extract(block.data[rows]).astype(np.int64)
            last = self._last[m.name]
            prev = np.empty(len(c), np.int64)
            prev[0] = c[0] - 1 if last is None else last
            prev[1:] = c[:-1]
            d = (c - prev) % mod
            if np.all(d == 1):  # the common case: in order
                self._last[m.name] = int(c[-1])
                continue
            if not copied:
                block = FrameBlock(*(getattr(block, f).copy() for f in
                                     ("t", "arbitration_id", "is_extended", "is_remote",
                                      "is_error", "dlc", "data")))
                copied = True
            src = list(range(len(c)))  # row k takes the contents of row src[k]
            c = c.tolist()
            n = len(c)
            first = int(prev[0])
            held_from = n
            # only the rows out of sequence are looked at, in order (a heap: a rotation
            # puts the rows after it up for a look again); row i's predecessor is c[i-1]
            todo = np.flatnonzero(d != 1).tolist()
            heapq.heapify(todo)
            seen = -1
            while todo:
                i = heapq.heappop(todo)
                if i <= seen:
                    continue
                seen = i
                cur = first if i == 0 else c[i - 1]
                gap = (c[i] - cur) % mod
                if not 2 <= gap <= 1 + self.window:
                    continue
                want = (cur + 1) % mod
                ahead = [j for j in range(i + 1, min(n, i + 1 + self.window)) if c[j] == want]
                if ahead:
                    j = ahead[0]
                    # rotate the contents of rows i..j: j's up to i, the others down
                    src[i:j + 1] = [src[j], *src[i:j]]
                    c[i:j + 1] = [c[j], *c[i:j]]
                    self.moved += 1
                    for k in range(i + 1, min(n, j + 2)):
                        heapq.heappush(todo, k)
                elif i == n - 1:
                    held_from = i  # its neighbour may be the next block's first
            cur = c[held_from - 1] if held_from > 0 else first
            take = rows[np.asarray(src, np.intp)]
            for f in _CONTENT:
                a = getattr(block, f)
                a[rows] = a[take]
            if held_from < n:
                hold[rows[held_from:]] = True
            self._last[m.name] = cur
        if hold.any():
            self._held = block.take(hold)
            block = block.take(~hold)
        return block

    def flush(self) -> FrameBlock:
        """End of stream: the frames still held, as they came."""
        held, self._held = self._held, None
        return held if held is not None else FrameBlock.empty()
