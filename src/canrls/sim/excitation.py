"""Speed-reference profiles that excite the drive: reversals, chirps, steps and PRBS.

A profile maps time to the speed reference and its derivative (the acceleration the
speed controller feeds forward), ``w_ref, a_ref = profile.reference(t)``, for all
``t >= 0``; profiles add (``a + b``), play in turn (:class:`Sequence`) and scale
(``profile.scaled(k)``). The named presets (:data:`PRESETS`, :func:`excitation`):
docs/simulator.md, "Excitation".
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Callable
from collections.abc import Sequence as Seq

import numpy as np
import numpy.typing as npt

from canrls.core.errors import ConfigError

__all__ = [
    "Excitation",
    "Ramps",
    "Chirp",
    "Sequence",
    "Sum",
    "Scaled",
    "constant",
    "reversals",
    "phases",
    "steps",
    "prbs",
    "chirp",
    "standard",
    "PRESETS",
    "excitation",
]

F64 = npt.NDArray[np.float64]


class Excitation(ABC):
    """A speed reference ``w_ref(t)`` with its derivative ``a_ref(t)``."""

    #: Repetition period [s], or None when the profile holds its final value.
    period: float | None = None
    name: str = "excitation"

    @abstractmethod
    def reference(self, t: npt.ArrayLike) -> tuple[F64, F64]:
        """Speed reference and acceleration at times ``t`` (arrays of the shape of t)."""

    def duration(self) -> float:
        """Length of one cycle (or of the transient part of a non-periodic profile)."""
        return self.period if self.period is not None else 0.0

    def __add__(self, other: Excitation) -> Sum:
        return Sum([self, other])

    def scaled(self, k: float) -> Excitation:
        """Speed and acceleration times ``k`` (same timing)."""
        return self if k == 1.0 else Scaled(self, k)

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.name}>"


class Ramps(Excitation):
    """Piecewise-linear speed through breakpoints ``(times[j], speeds[j])``.

    ``times`` start at 0 and increase strictly. Periodic: repeats every ``times[-1]``
    (``speeds[-1]`` should equal ``speeds[0]``); otherwise holds ``speeds[-1]``.
    """

    def __init__(self, times: Seq[float], speeds: Seq[float], periodic: bool = True,
                 name: str = "ramps") -> None:
        tt = np.asarray(times, dtype=np.float64)
        ww = np.asarray(speeds, dtype=np.float64)
        if tt.ndim != 1 or tt.shape != ww.shape or len(tt) < 2:
            raise ConfigError(f"excitation {name}: need >= 2 breakpoints of equal count")
        if tt[0] != 0.0 or np.any(np.diff(tt) <= 0):
            raise ConfigError(f"excitation {name}: breakpoint times must start at 0 and increase")
        self.times, self.speeds = tt, ww
        self._slope = np.diff(ww) / np.diff(tt)
        self.period = float(tt[-1]) if periodic else None
        self._end = float(tt[-1])
        self.name = name

    def duration(self) -> float:
        return self._end

    def reference(self, t: npt.ArrayLike) -> tuple[F64, F64]:
        t = np.asarray(t, dtype=np.float64)
        tm = np.mod(t, self.period) if self.period is not None else t
        w = np.interp(tm, self.times, self.speeds)
        j = np.clip(np.searchsorted(self.times, tm, side="right") - 1, 0, len(self._slope) - 1)
        a = self._slope[j]
        if self.period is None:
            a = np.where(tm >= self._end, 0.0, a)
        return w, a


class Chirp(Excitation):
    r"""Linear frequency sweep around ``offset``, repeated every ``sweep_time``.

    .. math::

        \omega_{ref} = w_0 + A \sin 2\pi\varphi(t),\quad
        \varphi(t) = f_0 t + (f_1 - f_0) t^2 / (2 T)

    ``f1`` is adjusted (by :func:`chirp`) so that a sweep holds a whole number of
    cycles: the speed is continuous where it repeats.
    """

    def __init__(self, amplitude: float, f0: float, f1: float, sweep_time: float,
                 offset: float = 0.0, name: str = "chirp") -> None:
        if not sweep_time > 0 or f0 < 0 or f1 < 0:
            raise ConfigError(f"excitation {name}: need sweep_time > 0 and f0, f1 >= 0")
        self.amplitude, self.f0, self.f1, self.sweep_time, self.offset = (
            float(amplitude), float(f0), float(f1), float(sweep_time), float(offset))
        self.period: float = self.sweep_time
        self.name = name

    def reference(self, t: npt.ArrayLike) -> tuple[F64, F64]:
        tm = np.mod(np.asarray(t, dtype=np.float64), self.period)
        T, f0, f1, A = self.sweep_time, self.f0, self.f1, self.amplitude
        # phi = f0 t + (f1 - f0) t^2 / (2T);  f = dphi/dt = f0 + (f1 - f0) t / T
        phi = f0 * tm + (f1 - f0) * tm * tm / (2.0 * T)
        f = f0 + (f1 - f0) * tm / T
        w = self.offset + A * np.sin(2.0 * np.pi * phi)
        a = A * 2.0 * np.pi * f * np.cos(2.0 * np.pi * phi)
        return w, a


class Sequence(Excitation):
    """Profiles played one after the other, each for ``duration`` (default: one cycle); repeats."""

    def __init__(self, parts: Seq[Excitation | tuple[Excitation, float]],
                 name: str = "sequence") -> None:
        self.parts: list[tuple[Excitation, float]] = []
        for p in parts:
            ex, d = (p, p.duration()) if isinstance(p, Excitation) else p
            if not d > 0:
                raise ConfigError(f"excitation {name}: part {ex.name} needs a duration > 0")
            self.parts.append((ex, float(d)))
        if not self.parts:
            raise ConfigError(f"excitation {name}: empty sequence")
        self.starts = np.cumsum([0.0] + [d for _, d in self.parts])
        self.period: float = float(self.starts[-1])
        self.name = name

    def reference(self, t: npt.ArrayLike) -> tuple[F64, F64]:
        tm = np.mod(np.asarray(t, dtype=np.float64), self.period)
        w = np.zeros_like(tm)
        a = np.zeros_like(tm)
        seg = np.clip(np.searchsorted(self.starts, tm, side="right") - 1, 0, len(self.parts) - 1)
        for j, (ex, _d) in enumerate(self.parts):
            m = seg == j
            if np.any(m):
                w[m], a[m] = ex.reference(tm[m] - self.starts[j])
        return w, a


class Sum(Excitation):
    """The sum of several profiles (each keeps its own period)."""

    def __init__(self, parts: Seq[Excitation], name: str | None = None) -> None:
        self.parts = list(parts)
        if not self.parts:
            raise ConfigError("excitation sum: no parts")
        periods = [p.period for p in self.parts]
        self.period = periods[0] if all(p == periods[0] for p in periods) else None
        self.name = name or "+".join(p.name for p in self.parts)

    def duration(self) -> float:
        return max(p.duration() for p in self.parts)

    def reference(self, t: npt.ArrayLike) -> tuple[F64, F64]:
        t = np.asarray(t, dtype=np.float64)
        w = np.zeros_like(t)
        a = np.zeros_like(t)
        for p in self.parts:
            wp, ap = p.reference(t)
            w += wp
            a += ap
        return w, a


class Scaled(Excitation):
    """A profile with speed and acceleration multiplied by ``k``."""

    def __init__(self, base: Excitation, k: float) -> None:
        self.base, self.k = base, float(k)
        self.period = base.period
        self.name = base.name

    def duration(self) -> float:
        return self.base.duration()

    def reference(self, t: npt.ArrayLike) -> tuple[F64, F64]:
        w, a = self.base.reference(t)
        return w * self.k, a * self.k


# ---------------------------------------------------------------------------- factories


def constant(speed: float, accel: float = 300.0) -> Ramps:
    """Ramp from rest to ``speed`` at ``accel`` and stay there (one direction, not periodic)."""
    if accel <= 0:
        raise ConfigError(f"excitation constant: accel {accel!r} must be > 0")
    tr = max(abs(speed) / accel, 1e-9)
    return Ramps([0.0, tr], [0.0, speed], periodic=False, name="constant")


def reversals(speed: float, accel: float = 300.0, hold: float = 2.0) -> Ramps:
    """Trapezoidal speed reversals: 0 -> +speed, hold, -> -speed, hold, -> 0; repeats."""
    if speed <= 0 or accel <= 0 or hold < 0:
        raise ConfigError("excitation reversals: need speed > 0, accel > 0, hold >= 0")
    r = speed / accel
    tt = [0.0, r, r + hold, 3 * r + hold, 3 * r + 2 * hold, 4 * r + 2 * hold]
    ww = [0.0, speed, speed, -speed, -speed, 0.0]
    if hold == 0:
        tt = [0.0, r, 3 * r, 4 * r]
        ww = [0.0, speed, -speed, 0.0]
    return Ramps(tt, ww, name=f"reversals({speed:g})")


def phases(speeds: Seq[float], accel: float = 300.0,
           holds: float | Seq[float] = 2.0) -> Sequence:
    """Slow and fast phases: one cycle of :func:`reversals` at each speed, in order."""
    hs = [float(holds)] * len(speeds) if isinstance(holds, (int, float)) else list(holds)
    if len(hs) != len(speeds):
        raise ConfigError("excitation phases: one hold per speed")
    return Sequence([reversals(v, accel, h) for v, h in zip(speeds, hs, strict=True)],
                    name="phases")


def steps(levels: Seq[float], hold: float = 1.0, accel: float = 2000.0) -> Ramps:
    """Speed steps through ``levels`` then back to 0, each held ``hold`` s; repeats.

    Steps are steep ramps at ``accel``.
    """
    if hold <= 0 or accel <= 0:
        raise ConfigError("excitation steps: need hold > 0 and accel > 0")
    return _levels([0.0, *levels, 0.0], hold, accel, name="steps")


def _levels(levels: Seq[float], hold: float, accel: float, name: str) -> Ramps:
    tt, ww = [0.0], [float(levels[0])]
    t = 0.0
    for j in range(1, len(levels)):
        prev, new = float(levels[j - 1]), float(levels[j])
        if new != prev:
            t += abs(new - prev) / accel
            tt.append(t)
            ww.append(new)
        if j < len(levels) - 1:
            t += hold
            tt.append(t)
            ww.append(new)
    if len(tt) < 2:
        tt, ww = [0.0, hold], [ww[0], ww[0]]
    return Ramps(tt, ww, name=name)


# maximal-length LFSR taps (Fibonacci, bit positions counted from 1)
_TAPS = {5: (5, 3), 6: (6, 5), 7: (7, 6), 9: (9, 5), 10: (10, 7), 11: (11, 9), 15: (15, 14)}


def _mseq(order: int, seed: int) -> npt.NDArray[np.int8]:
    if order not in _TAPS:
        raise ConfigError(f"excitation prbs: order {order} not one of {sorted(_TAPS)}")
    n = (1 << order) - 1
    state = (int(np.random.default_rng(seed).integers(1, n + 1))) & n or 1
    a, b = _TAPS[order]
    out = np.empty(n, dtype=np.int8)
    for j in range(n):
        out[j] = state & 1
        bit = ((state >> (order - a)) ^ (state >> (order - b))) & 1
        state = (state >> 1) | (bit << (order - 1))
    return out


def prbs(amplitude: float, bit_time: float = 0.04, order: int = 7, accel: float = 1000.0,
         offset: float = 0.0, seed: int = 0) -> Ramps:
    """Pseudo-random binary speed: ``offset ± amplitude`` switching on a maximal-length sequence.

    One cycle holds ``2**order - 1`` bits of ``bit_time`` s, ramps at ``accel``, starts
    and ends at rest; ``seed`` picks where the sequence starts.
    """
    if amplitude <= 0 or bit_time <= 0 or accel <= 0:
        raise ConfigError("excitation prbs: need amplitude > 0, bit_time > 0, accel > 0")
    bits = _mseq(order, seed)
    lv = [offset + (amplitude if b else -amplitude) for b in bits]
    return _levels([0.0, *lv, 0.0], bit_time, accel, name="prbs")


def chirp(amplitude: float, f0: float, f1: float, sweep_time: float,
          offset: float = 0.0) -> Chirp:
    """A :class:`Chirp`, ``f1`` rounded so that the sweep holds a whole number of cycles."""
    cycles = max(1, round((f0 + f1) / 2.0 * sweep_time))
    f1r = 2.0 * cycles / sweep_time - f0
    return Chirp(amplitude, f0, f1r, sweep_time, offset, name="chirp")


def standard(seed: int = 0) -> Sequence:
    """The identification profile (docs/simulator.md, "Excitation")."""
    return Sequence([
        phases([100.0, 40.0, 10.0, 2.0, 0.5], accel=300.0, holds=[1.5, 2.0, 2.0, 3.0, 3.0]),
        chirp(20.0, 0.2, 15.0, 10.0),
        prbs(5.0, 0.04, order=7, accel=1000.0, seed=seed),
    ], name="standard")


#: Named presets (rotary units); each takes the seed.
PRESETS: dict[str, Callable[[int], Excitation]] = {
    "standard": standard,
    "poor": lambda seed: constant(20.0),
    "reversals": lambda seed: reversals(20.0, 300.0, 2.0),
    "slow": lambda seed: phases([0.5, 1.0, 2.0], accel=20.0, holds=3.0),
    "fast": lambda seed: phases([50.0, 100.0], accel=500.0, holds=1.0),
    "chirp": lambda seed: chirp(20.0, 0.2, 15.0, 10.0),
    "steps": lambda seed: steps([10.0, -10.0, 30.0, -30.0, 5.0, -5.0], hold=1.0),
    "prbs": lambda seed: prbs(5.0, 0.04, order=7, seed=seed),
}


def excitation(spec: str | Excitation, scale: float = 1.0, seed: int = 0) -> Excitation:
    """A profile by name (``"standard"``), sum of names (``"reversals+prbs"``) or as given.

    ``scale`` multiplies speed and acceleration (rad/s -> the axis's unit).
    """
    if isinstance(spec, Excitation):
        return spec
    names = [s.strip() for s in str(spec).split("+") if s.strip()]
    if not names:
        raise ConfigError(f"excitation: empty spec {spec!r}")
    parts = []
    for name in names:
        if name not in PRESETS:
            raise ConfigError(f"excitation: unknown profile {name!r}; known: {', '.join(PRESETS)}")
        parts.append(PRESETS[name](seed))
    ex = parts[0] if len(parts) == 1 else Sum(parts)
    if not math.isfinite(scale) or scale <= 0:
        raise ConfigError(f"excitation: scale {scale!r} must be > 0")
    return ex.scaled(scale)
