"""A block of raw CAN frames as arrays: the unit that moves between the edges and the pipeline.

Log readers, the live bus listener and the simulated drive all produce
:class:`FrameBlock` objects; strict decoding turns them into
:class:`~canrls.core.samples.Signals`. Arrays rather than one object per frame keep
the offline replay fast, and the same code serves the live path (a block of
whatever frames arrived).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import can
import numpy as np
import numpy.typing as npt

from canrls.core.errors import DecodeError

__all__ = ["FrameBlock", "MAX_DATA_LENGTH"]

#: Most data bytes a CAN frame carries (CAN FD); a longer one is refused, never truncated.
MAX_DATA_LENGTH = 64


@dataclass(frozen=True)
class FrameBlock:
    """N CAN frames (structure of arrays).

    Attributes
    ----------
    t : float64 (N,)            receive timestamps [s]
    arbitration_id : uint32 (N,)
    is_extended : bool (N,)
    is_remote : bool (N,)
    is_error : bool (N,)        error frames (bus errors, bus-off notifications)
    dlc : uint8 (N,)            data length in bytes (0..8 classic, up to 64 for CAN FD)
    data : uint8 (N, W)         payload, zero-padded to the block's width W (>= 8)
    """

    t: npt.NDArray[np.float64]
    arbitration_id: npt.NDArray[np.uint32]
    is_extended: npt.NDArray[np.bool_]
    is_remote: npt.NDArray[np.bool_]
    is_error: npt.NDArray[np.bool_]
    dlc: npt.NDArray[np.uint8]
    data: npt.NDArray[np.uint8]

    def __post_init__(self) -> None:
        n = len(self.t)
        for name in ("arbitration_id", "is_extended", "is_remote", "is_error", "dlc"):
            if len(getattr(self, name)) != n:
                raise ValueError(f"FrameBlock.{name} has {len(getattr(self, name))} rows, "
                                 f"t has {n}")
        if self.data.ndim != 2 or self.data.shape[0] != n:
            raise ValueError(f"FrameBlock.data must be (N, W) with N={n}, got {self.data.shape}")

    def __len__(self) -> int:
        return len(self.t)

    @staticmethod
    def empty(width: int = 8) -> FrameBlock:
        return FrameBlock.allocate(0, width)

    @staticmethod
    def allocate(n: int, width: int = 8) -> FrameBlock:
        """A zeroed block of ``n`` standard data frames, to be filled in place."""
        return FrameBlock(
            t=np.zeros(n, np.float64),
            arbitration_id=np.zeros(n, np.uint32),
            is_extended=np.zeros(n, np.bool_),
            is_remote=np.zeros(n, np.bool_),
            is_error=np.zeros(n, np.bool_),
            dlc=np.zeros(n, np.uint8),
            data=np.zeros((n, max(8, width)), np.uint8),
        )

    @staticmethod
    def from_messages(messages: Sequence[can.Message]) -> FrameBlock:
        """Pack python-can messages into a block."""
        n = len(messages)
        width = max([8] + [len(m.data) for m in messages])
        if width > MAX_DATA_LENGTH:
            m = next(m for m in messages if len(m.data) > MAX_DATA_LENGTH)
            raise DecodeError(f"frame 0x{m.arbitration_id:X} at t = {m.timestamp}: "
                              f"{len(m.data)} data bytes, a CAN frame carries at most "
                              f"{MAX_DATA_LENGTH}", reason="length")
        b = FrameBlock.allocate(n, width)
        for k, m in enumerate(messages):
            b.t[k] = m.timestamp
            b.arbitration_id[k] = m.arbitration_id
            b.is_extended[k] = m.is_extended_id
            b.is_remote[k] = m.is_remote_frame
            b.is_error[k] = m.is_error_frame
            d = bytes(m.data)
            b.dlc[k] = len(d)
            b.data[k, : len(d)] = np.frombuffer(d, np.uint8)
        return b

    def to_messages(self, channel: str | None = None) -> list[can.Message]:
        """Unpack into python-can messages."""
        out = []
        for k in range(len(self)):
            dlc = int(self.dlc[k])
            out.append(can.Message(
                timestamp=float(self.t[k]),
                arbitration_id=int(self.arbitration_id[k]),
                is_extended_id=bool(self.is_extended[k]),
                is_remote_frame=bool(self.is_remote[k]),
                is_error_frame=bool(self.is_error[k]),
                dlc=dlc,
                data=b"" if self.is_remote[k] else self.data[k, :dlc].tobytes(),
                is_fd=dlc > 8,
                channel=channel,
            ))
        return out

    def take(self, index: npt.NDArray[np.intp] | npt.NDArray[np.bool_] | slice) -> FrameBlock:
        """Rows selected by an index array, a mask or a slice."""
        return FrameBlock(self.t[index], self.arbitration_id[index], self.is_extended[index],
                          self.is_remote[index], self.is_error[index], self.dlc[index],
                          self.data[index])

    @staticmethod
    def concat(blocks: Iterable[FrameBlock]) -> FrameBlock:
        bl = [b for b in blocks]
        if not bl:
            return FrameBlock.empty()
        width = max(b.data.shape[1] for b in bl)
        data = np.concatenate([
            b.data if b.data.shape[1] == width
            else np.pad(b.data, ((0, 0), (0, width - b.data.shape[1]))) for b in bl
        ])
        return FrameBlock(
            np.concatenate([b.t for b in bl]),
            np.concatenate([b.arbitration_id for b in bl]),
            np.concatenate([b.is_extended for b in bl]),
            np.concatenate([b.is_remote for b in bl]),
            np.concatenate([b.is_error for b in bl]),
            np.concatenate([b.dlc for b in bl]),
            data,
        )
