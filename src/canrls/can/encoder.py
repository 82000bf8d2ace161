"""Feedback frames from SI arrays (:class:`FeedbackEncoder`): the inverse of the decoder,
for the simulated drive and the tests."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from canrls.can.codec import (
    crc_vector,
)
from canrls.can.frameblock import FrameBlock
from canrls.core.units import axis_of

if TYPE_CHECKING:
    from canrls.can.protocol import Protocol

__all__ = ["FeedbackEncoder"]


class FeedbackEncoder:
    """Encode SI arrays into the mapped feedback frames (the inverse of :class:`Decoder`).

    One frame per mapped message and period, interleaved in the protocol's message
    order (the current's message first); every message of a period carries the same
    alive counter (mod its range), and the E2E CRC is computed as
    :func:`canrls.can.e2e.e2e_crc` does. Raw values are rounded to nearest (half to even,
    as cantools) and checked against the DBC range: out of range raises
    :class:`EncodeError` naming the signal and the value, unless ``clip=True``, which
    clips and counts in ``clipped`` (signal -> count).

    A position signal whose bit field spans exactly one turn (e.g. 16 bits of
    2*pi/65536 rad) is encoded modulo one turn, so unwrapped angles can be passed.

    Parameters
    ----------
    protocol : the :class:`Protocol` (its feedback messages and mapping).
    clip : clip out-of-range values instead of raising (for the simulator).
    counter : alive counter of the first period.
    stagger : time [s] between the frames of one period (message k at ``t + k*stagger``).
    """

    def __init__(self, protocol: Protocol, *, clip: bool = False, counter: int = 0,
                 stagger: float = 0.0) -> None:
        self.protocol = protocol
        self.clip = clip
        self.counter = int(counter)
        self.stagger = float(stagger)
        self.clipped: dict[str, int] = {}
        #: roles encoded modulo one turn (a full-turn position field)
        self.wrapping: frozenset[str] = frozenset(
            r.role for r in protocol.roles.values()
            if r.role == "position" and not r.codec.is_float and axis_of(r.unit) == "rotary"
            and abs((1 << r.codec.length) * abs(r.si_per_raw) - 2 * math.pi) <= 1e-9 * 2 * math.pi)
        self._width = max(8, max(m.length for m in protocol.messages))

    def encode(self, t: npt.ArrayLike, current: npt.ArrayLike | None, speed: npt.ArrayLike,
               position: npt.ArrayLike | None = None,
               voltage: npt.ArrayLike | None = None,
               torque: npt.ArrayLike | None = None) -> FrameBlock:
        """Frames of ``len(t)`` periods (``len(t) * len(protocol.messages)`` frames).

        Values are SI (A, rad/s, rad, V, N·m). A mapped role given as ``None`` is sent
        as raw 0; a role given but not mapped is ignored.
        """
        p = self.protocol
        tt = np.asarray(t, np.float64).ravel()
        n = len(tt)
        si = {"current": current, "speed": speed, "position": position, "voltage": voltage,
              "torque": torque}
        m_count = len(p.messages)
        block = FrameBlock.allocate(n * m_count, self._width)
        seq = self.counter + np.arange(n, dtype=np.int64)
        for k, m in enumerate(p.messages):
            data = np.zeros((n, self._width), np.uint8)
            for r in m.roles:
                v = si[r.role]
                if v is None:
                    continue
                arr = np.asarray(v, np.float64).ravel()
                if len(arr) != n:
                    raise ValueError(f"{r.role} has {len(arr)} samples, t has {n}")
                dbc_units = arr / r.si_scale if r.si_scale != 1.0 else arr
                raw, n_clip = r.codec.to_raw(dbc_units, clip=self.clip,
                                             wrap=r.role in self.wrapping)
                if n_clip:
                    self.clipped[r.codec.qualname] = self.clipped.get(r.codec.qualname, 0) + n_clip
                r.codec.insert(data, raw)
            if m.counter is not None:
                m.counter.insert(data, seq % (1 << m.counter.length))
            if m.crc is not None:
                data[:, 0] = crc_vector(m.frame_id, data, m.length)
            sl = slice(k, None, m_count)
            block.t[sl] = tt + k * self.stagger
            block.arbitration_id[sl] = m.frame_id
            block.is_extended[sl] = m.is_extended
            block.dlc[sl] = m.length
            block.data[sl] = data
        self.counter += n
        return block
