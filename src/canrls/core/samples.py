"""Samples: the pipeline's input, one row per control period.

A :class:`Signals` block holds paired measurements as float64 arrays in SI units
(rotary axis: rad, rad/s, A, V, N·m; linear axis: m, m/s, A, V, N). Position is as
measured (single-turn or wrapping); the pipeline unwraps it. Optional channels are
``None`` when the drive does not send them: a drive reports current or torque (a
CiA 402 drive's torque actual value) or both, and speed always.

A long record kept out of memory is :mod:`canrls.core.spill`'s.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

__all__ = ["Signals", "ROLES"]

F64 = npt.NDArray[np.float64]

#: The signal roles a DBC mapping can fill.
ROLES: tuple[str, ...] = ("current", "speed", "position", "voltage", "torque")


@dataclass(frozen=True)
class Signals:
    """A block of paired samples (structure of arrays, all of length N).

    ``current`` is ``None`` for a drive that reports its torque instead (``torque``,
    N·m; a force in N on a linear axis); one of the two is always there.
    """

    t: F64
    current: F64 | None
    speed: F64
    position: F64 | None = None
    voltage: F64 | None = None
    torque: F64 | None = None

    def __post_init__(self) -> None:
        n = len(self.t)
        for name in ROLES:
            v = getattr(self, name)
            if v is not None and len(v) != n:
                raise ValueError(f"Signals.{name} has {len(v)} samples, t has {n}")

    @classmethod
    def from_roles(cls, columns: Mapping[str, F64 | None]) -> Signals:
        """A block from ``{"t": ..., role: array}`` (a role absent or ``None``: not sent)."""
        t, speed = columns["t"], columns["speed"]
        assert t is not None and speed is not None
        return cls(t, columns.get("current"), speed, columns.get("position"),
                   columns.get("voltage"), columns.get("torque"))

    def __len__(self) -> int:
        return len(self.t)

    def has(self, role: str) -> bool:
        """True when the optional channel ``role`` is present."""
        return getattr(self, role) is not None

    def slice(self, start: int, stop: int) -> Signals:
        """Rows ``start:stop`` as a new block (views, no copy)."""

        def s(a: F64 | None) -> F64 | None:
            return None if a is None else a[start:stop]

        return Signals(self.t[start:stop], s(self.current), self.speed[start:stop],
                       s(self.position), s(self.voltage), s(self.torque))

    @staticmethod
    def concat(blocks: list[Signals]) -> Signals:
        """Join blocks end to end (optional channels must be present in all or none)."""
        if not blocks:
            e = np.zeros(0)
            return Signals(e, e.copy(), e.copy())

        def cat(name: str) -> F64 | None:
            vs = [getattr(b, name) for b in blocks]
            if any(v is None for v in vs):
                return None
            return np.concatenate(vs)

        return Signals(np.concatenate([b.t for b in blocks]), cat("current"),
                       np.concatenate([b.speed for b in blocks]),
                       cat("position"), cat("voltage"), cat("torque"))
