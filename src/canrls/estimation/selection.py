r"""Which samples update the estimators: the one sample-selection policy.

The live daemon, the offline replay and the diagnosis all decide with
:class:`SamplePolicy`, so a recording gives the same used samples (and the same
filtered columns) wherever it is processed:

1. **Gap filling.** A lost frame leaves its period without a sample; a gap of ``m``
   missing periods, up to ``gap`` seconds, is filled with ``m`` interpolated rows
   (:class:`GapFiller`). Filled rows pass through the filter but never update the
   estimators; a longer gap (or time going backwards) restarts the filter.
   A fill the neighbours show to be wrong (the signal steps or bends inside the gap:
   the straight line there is off by far more than the noise) is *doubtful*: the
   ``warmup`` rows after it, which carry it in the filter's memory, are not used
   either (:meth:`GapFiller.settling`).
2. **Warm-up.** After the start and after every restart, ``warmup`` samples are not
   used: the filter's zero initial state does not match the signals there.
3. **Speed limits.** A sample with ``|omega| < min_speed`` (sign-dependent friction
   near a reversal: the measured speed's sign is noise and the drive sticks) or
   ``|omega| > max_speed`` (the fastest position-periodic column advances more than
   ``max_phase_step`` rad per sample) is not used, nor are the ``warmup`` samples after
   it. With a minimum speed, a speed whose sign changed since the last sample counts
   as below it: the drive reversed between the two samples (a fast reversal passes
   through the band without a sample in it).

With the highest position order :math:`k` among the equation's effects,

.. math::

    \omega_{max} = \frac{\Delta\vartheta_{max}}{k\,T_s}
    \quad(\text{linear axis: } \times\,\text{pitch}/2\pi), \qquad
    n_{warm} = \Big\lceil \frac{5}{\zeta\,\omega_c\,T_s} \Big\rceil

(:math:`\omega_c = 2\pi f_c` of the state-variable filter) unless the settings give
them. The policy is a frozen value; the state carried between blocks lives in the
:class:`GapFiller` and :class:`SampleSelector` it makes.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Protocol, TypeVar, overload

import numpy as np
import numpy.typing as npt

from canrls import _kernels
from canrls.core.errors import ConfigError
from canrls.core.samples import ROLES, Signals
from canrls.core.spill import ColumnLike, MaskPacker, PackedMask, SpilledSignals
from canrls.estimation.equation import Equation
from canrls.estimation.svf import MAX_TIME_CONSTANT

#: Most samples of warm-up (``[estimator] warmup_s``): five of the state-variable filter's
#: longest time constant (:data:`~canrls.estimation.svf.MAX_TIME_CONSTANT`), what the
#: default warm-up can be.
MAX_WARMUP = 5 * MAX_TIME_CONSTANT

__all__ = ["MAX_WARMUP", "SelectionSettings", "SamplePolicy", "GapFiller", "SampleSelector",
           "Selection", "SelectedSamples", "FilledRecord", "FILL_DOUBT", "NOISE_ROWS", "CHECKED"]

F64 = npt.NDArray[np.float64]
B = npt.NDArray[np.bool_]
_G = TypeVar("_G", bound=np.generic)

#: A filled gap is doubtful when the straight line across it departs from the slope
#: before it by more than this many times the signal's noise (:meth:`GapFiller.settling`):
#: far beyond the noise's own spread there (1.9 sigma for one missing sample), the
#: signal stepped or bent inside the gap.
FILL_DOUBT = 8.0
#: Measured rows before a gap on which the signal's noise is measured.
NOISE_ROWS = 64
#: The signals whose fills are checked. The position is not: its straight line is off
#: by the acceleration's share (``a dt^2 / 4``), far below anything the filter sees.
CHECKED = ("current", "speed", "voltage", "torque")


class SelectionSettings(Protocol):
    """The estimator settings the policy reads
    (:class:`canrls.estimation.pipeline.EstimatorSettings` has them)."""

    @property
    def warmup_s(self) -> float | None: ...

    @property
    def gap_periods(self) -> float: ...

    @property
    def max_phase_step(self) -> float: ...

    @property
    def min_speed(self) -> float | None: ...


def _phase_speed_limit(max_phase_step: float, order: int, dt: float,
                       pitch: float | None) -> float:
    """Largest |speed| at which a column of position ``order`` advances at most
    ``max_phase_step`` rad per sample (``inf`` for order 0)."""
    if not order:
        return math.inf
    # k * |omega| * dt <= max_phase_step
    limit = max_phase_step / (order * dt)
    if pitch is not None:
        # the phase of a linear axis advances 2 pi / pitch per metre
        limit *= pitch / (2 * math.pi)
    return limit


# -------------------------------------------------------------------------- policy
@dataclass(frozen=True)
class SamplePolicy:
    """What decides which samples update the estimators of one equation.

    Attributes
    ----------
    dt : sample period [s]
    warmup : samples not used after a (re)start of the filter, and after a sample
        outside the speed limits
    gap : a step of the sample times longer than this [s] (or backwards) restarts the
        filter; shorter gaps are filled
    wrap : period of the measured position (the shorter way round when filling), or
        ``None``
    min_speed, max_speed : the used samples have ``min_speed <= |omega| <= max_speed``
    max_phase_step : largest phase advance per sample of a periodic column [rad]
    pitch : linear axis: metres per period of the periodic terms (``None``: rotary)
    doubt : a filled gap is doubtful when the straight line across it departs from the
        slope before it by more than ``doubt`` times the signal's noise
        (:meth:`GapFiller.settling`; ``inf``: never; ``None``: :data:`FILL_DOUBT`)
    """

    dt: float
    warmup: int
    gap: float
    wrap: float | None
    min_speed: float = 0.0
    max_speed: float = math.inf
    max_phase_step: float = math.inf
    pitch: float | None = None
    doubt: float | None = None

    @classmethod
    def for_equation(cls, equation: Equation, dt: float,
                     settings: SelectionSettings) -> SamplePolicy:
        """The policy of ``equation`` sampled every ``dt`` seconds, with ``settings``
        (:class:`~canrls.estimation.pipeline.EstimatorSettings`)."""
        s = settings
        dt = float(dt)
        m = equation.model
        wc = 2 * math.pi * m.cutoff_hz
        warm_s = 5.0 / (m.zeta * wc) if s.warmup_s is None else s.warmup_s
        # the warm-up sizes the residual's colour window (64 of them): bounded as the
        # filter's own (5 of its longest time constant), before anything is allocated
        if not warm_s / dt <= MAX_WARMUP:
            raise ConfigError(
                f"estimator.warmup_s = {warm_s!r}: {warm_s / dt:.3g} samples of warm-up at "
                f"the period {dt:g} s, at most {MAX_WARMUP} (the filter's longest warm-up: "
                f"warmup_s <= {MAX_WARMUP * dt:g} s)")
        pitch = m.pitch if m.axis == "linear" else None
        k_max = max([e.order for e in equation.effects] + [0])
        friction = any(e.name in ("coulomb", "stribeck") for e in equation.effects)
        if not friction:
            min_speed = 0.0
        else:
            min_speed = 5.0 * m.coulomb_band if s.min_speed is None else s.min_speed
        return cls(dt=dt, warmup=int(math.ceil(warm_s / dt)), gap=s.gap_periods * dt,
                   wrap=2.0 * math.pi if m.axis == "rotary" else m.wrap,
                   min_speed=min_speed,
                   max_speed=_phase_speed_limit(s.max_phase_step, k_max, dt, pitch),
                   max_phase_step=s.max_phase_step, pitch=pitch)

    def for_order(self, order: int) -> SamplePolicy:
        """The policy for a periodic column of position ``order`` alone: no low-speed
        limit, the high-speed limit of that order."""
        return dataclasses.replace(
            self, min_speed=0.0,
            max_speed=_phase_speed_limit(self.max_phase_step, order, self.dt, self.pitch))

    def filler(self) -> GapFiller:
        """A new gap filler (state: the previous samples) for a stream of blocks."""
        return GapFiller(self.dt, self.gap, self.wrap, settle=self.warmup, doubt=self.doubt)

    def selector(self) -> SampleSelector:
        """A new selector (state: last sample time, warm-up left) for a stream of blocks."""
        return SampleSelector(self)

    def apply(self, signals: Signals | SpilledSignals, block: int = 65536) -> SelectedSamples:
        """A whole record, as a pipeline fed it selects it: gaps filled, restarts and
        used rows marked (the filled rows never used). The record is filled and
        selected ``block`` samples at a time (the filler and the selector carry their
        state, so the masks are those of one block; they are kept packed, one bit a
        row); the filled record is not kept but filled again where read
        (:class:`FilledRecord`)."""
        filler, selector = self.filler(), self.selector()
        # the masks packed as they come (one bit a row)
        reals, restarts, uses, usables = MaskPacker(), MaskPacker(), MaskPacker(), MaskPacker()
        any_filled = any_settling = False
        for a in range(0, max(len(signals), 1), block):
            filled, real = filler.fill(signals.slice(a, min(len(signals), a + block)))
            settling = filler.settling(filled, real)
            sel = selector.select(filled.t, filled.speed)
            if real is None:
                real = np.ones(len(filled), np.bool_)
            else:
                any_filled = True
            usable = real
            if settling is not None:
                any_settling = True
                usable = real & ~settling
            reals.append(real)
            usables.append(usable)
            restarts.append(sel.restart)
            uses.append(sel.use & usable)
        real_all = reals.mask() if any_filled else None
        return SelectedSamples(signals=FilledRecord(signals, real_all, self),
                               real=real_all, restart=restarts.mask(), use=uses.mask(),
                               usable=usables.mask() if any_settling else real_all)


# --------------------------------------------------------------------------- state
@dataclass(frozen=True)
class Selection:
    """The rows of one block: where the filter restarts, which rows are used."""

    restart: B
    use: B
    restarts: int
    used: int


class SampleSelector:
    """Applies a :class:`SamplePolicy` block by block (the last sample time and the
    warm-up left are carried over, so the result does not depend on the block sizes)."""

    def __init__(self, policy: SamplePolicy) -> None:
        self.policy = policy
        self.reset()

    def reset(self) -> None:
        """The next sample starts the filter."""
        self._state = np.array([np.nan, 0.0, 0.0])

    def select(self, t: npt.ArrayLike, omega: npt.ArrayLike) -> Selection:
        """Restarts and used rows of a block with sample times ``t`` and speed ``omega``."""
        p = self.policy
        t_c = np.ascontiguousarray(t, dtype=np.float64)
        w = np.ascontiguousarray(omega, dtype=np.float64)
        n = len(t_c)
        restart = np.zeros(n, np.bool_)
        use = np.empty(n, np.bool_)
        # the C loop (canrls._kernels.select): a row restarts the filter when the time is
        # the first, steps back or jumps by more than ``gap``; it is not used while
        # ``warmup`` samples after a restart or after a speed out of limits are left
        restarts, used = _kernels.select(t_c, w, p.gap, p.warmup, p.min_speed, p.max_speed,
                                         self._state, restart, use)
        return Selection(restart, use, int(restarts), int(used))


def _quantum(v: F64) -> float:
    """The smallest nonzero difference between neighbouring values of ``v`` (the
    signal's resolution where it is quantised; 0 if ``v`` is constant)."""
    d = np.abs(np.diff(v))
    d = d[d > 0.0]
    return float(d.min()) if len(d) else 0.0


class GapFiller:
    r"""Fill short gaps in the sample times so the filter keeps its time base.

    A lost frame leaves its period without a sample; the filter, which assumes one
    sample per period, would then stretch the signals in time and bias the derivative
    columns (inertia). A gap of ``m`` missing periods, up to ``max_gap`` seconds, is
    filled with ``m`` rows interpolated on a straight line (the position along the
    shorter way round its wrap period). Filled rows pass through the filter but never
    update the estimators; longer gaps restart the filter instead. The previous sample
    is carried between blocks, so the result does not depend on the block sizes.

    The straight line is off by about the noise where the signal is smooth, and by far
    more where it steps or bends inside the gap (the speed controller's current at a
    step of the reference, the speed at the start of a ramp): the filter then carries
    an error hundreds of times a sample's noise into the ``settle`` rows after the gap
    (a few such gaps moved the simulated drive's parameters by 2 sigma, where
    thousands of fills on smooth stretches moved them by a tenth of that).
    :meth:`settling` marks those rows, for the estimators to leave out.
    """

    def __init__(self, dt: float, max_gap: float, period: float | None, settle: int = 0,
                 doubt: float | None = None) -> None:
        self.dt = dt
        self.max_gap = max_gap
        self.period = period
        #: rows after a doubtful fill not used (the filter's memory: its warm-up)
        self.settle = int(settle)
        #: the threshold of :meth:`settling`, in noise sigmas (None: :data:`FILL_DOUBT`)
        self.doubt = float(FILL_DOUBT if doubt is None else doubt)
        self._last: dict[str, float] | None = None
        self.reset()

    def reset(self) -> None:
        self._last = None
        #: the last rows of the checked signals (filled), for the noise before a gap
        self._recent: dict[str, F64] = {}
        #: rows of the next block still in the memory of a doubtful fill
        self._settle_left = 0
        #: doubtful fills so far
        self.doubtful = 0

    def settling(self, filled: Signals, real: B | None) -> B | None:
        r"""The rows of ``filled`` (the output of :meth:`fill`, ``real`` its mask) still
        in the filter's memory of a doubtful fill: from the gap's first filled row through
        the ``settle`` rows after it; ``None`` if none. Call it once after each
        :meth:`fill`, in order (the last rows are carried to the next block, so the
        result does not depend on the block sizes).

        A gap of ``m`` rows between the measured values :math:`v_p` and :math:`v_q`, of a
        checked signal (:data:`CHECKED`), is doubtful when the straight line's slope
        departs from the slope before the gap by more than ``doubt`` times the noise
        :math:`\sigma` of the :data:`NOISE_ROWS` rows before it:

        .. math::

            \Big|\frac{v_q - v_p}{m + 1} - (v_p - v_{p-1})\Big| > \text{doubt}\;\sigma,
            \qquad \sigma = \max\big(1.4826\,\mathrm{median}|\Delta^2 v| / \sqrt 6,\;
            q / \sqrt{12}\big)

        (white noise alone gives 1.9 sigma for ``m = 1``; a step ``D`` inside the gap
        ``D / 2``, where the straight line is off by ``D / 2``). ``q``, the smallest
        step between neighbouring values there, is the signal's resolution: a coarsely
        quantised signal (an encoder's speed, a current in whole LSBs) whose second
        differences are mostly zero has at least the rounding's noise, so a fill off by
        a step or two of resolution is not taken for a step of the signal.
        """
        n = len(filled)
        out: B | None = None
        if self._settle_left and n:
            out = np.zeros(n, np.bool_)
            out[:min(n, self._settle_left)] = True
        carry = max(0, self._settle_left - n)
        keep = NOISE_ROWS + 1
        roles = [r for r in CHECKED if filled.has(r)]
        if real is None:
            # no gap in the block (the common case): only the last rows are kept
            for r in roles:
                v = np.asarray(getattr(filled, r), dtype=np.float64)
                if n >= keep:
                    self._recent[r] = v[-keep:].copy()
                elif n:
                    old = self._recent.get(r, np.zeros(0))
                    self._recent[r] = np.concatenate([old, v])[-keep:]
            self._settle_left = carry
            return out
        cols: dict[str, tuple[F64, int]] = {}
        for r in roles:
            v = np.asarray(getattr(filled, r), dtype=np.float64)
            old = self._recent.get(r, np.zeros(0))
            cols[r] = (np.concatenate([old, v]), len(old))
        if n:
            gap = ~real
            starts = np.flatnonzero(gap & ~np.r_[False, gap[:-1]])
            stops = np.flatnonzero(gap & ~np.r_[gap[1:], False]) + 1
            for a, q in zip(starts.tolist(), stops.tolist(), strict=True):
                if not self._doubtful(cols, a, q):
                    continue
                self.doubtful += 1
                end = q + self.settle
                if out is None:
                    out = np.zeros(n, np.bool_)
                out[a:min(n, end)] = True
                carry = max(carry, end - n)
        self._settle_left = carry
        self._recent = {r: c[-keep:].copy() for r, (c, _) in cols.items()}
        return out

    def _doubtful(self, cols: dict[str, tuple[F64, int]], a: int, q: int) -> bool:
        """Whether the gap of filled rows ``a:q`` (rows of the block) is doubtful in one
        of ``cols`` (each: the carried rows then the block's, and the count carried)."""
        m = q - a
        for c, h in cols.values():
            # the measured rows on both sides, in the rows of c
            p, q_c = a - 1 + h, q + h
            if p < 2 or q_c >= len(c):
                # the start of the stream: too little before the gap to tell (fill never
                # leaves a gap at the end of a block: it fills on seeing the next sample)
                continue
            before = c[max(0, p - NOISE_ROWS):p + 1]
            # sigma = max(1.4826 median|d2 v| / sqrt(6), q / sqrt(12))
            sigma = max(1.4826 * float(np.median(np.abs(np.diff(before, 2)))) / math.sqrt(6.0),
                        _quantum(before) / math.sqrt(12.0))
            # |(v_q - v_p) / (m + 1) - (v_p - v_{p-1})| > doubt sigma
            if abs((c[q_c] - c[p]) / (m + 1) - (c[p] - c[p - 1])) > self.doubt * sigma:
                return True
        return False

    def fill(self, s: Signals) -> tuple[Signals, B | None]:
        """(signals with the gaps filled, mask of the real rows or ``None``: nothing filled)."""
        n = len(s)
        if n == 0:
            return s, None
        t = np.ascontiguousarray(s.t, dtype=np.float64)
        last = self._last
        row = {"t": float(t[-1])}
        for r in ROLES:
            v = getattr(s, r)
            if v is not None:
                row[r] = float(v[-1])
        self._last = row
        # the common case, decided in C (canrls._kernels.nothing_to_fill): no step misses
        # a period (each rounds to at most one, is longer than max_gap or not forward)
        if _kernels.nothing_to_fill(t, last is not None,
                                    last["t"] if last is not None else 0.0,
                                    self.dt, self.max_gap):
            return s, None
        prev_t = np.empty(n)
        prev_t[1:] = t[:-1]
        prev_t[0] = last["t"] if last is not None else t[0]
        gap = t - prev_t
        missing = np.rint(gap / self.dt).astype(np.int64) - 1
        missing[(gap > self.max_gap) | (gap <= 0) | (missing < 0)] = 0
        if not missing.any():
            return s, None
        total = n + int(missing.sum())
        # row k of the input lands at k + (filled rows before it)
        dest = np.arange(n) + np.cumsum(missing)
        real = np.zeros(total, np.bool_)
        real[dest] = True
        roles = [r for r in ROLES if s.has(r)]
        # every filled row at once: the gap it fills (owner k), its place i = 1..m in it
        ks = np.flatnonzero(missing)
        ms = missing[ks]
        owner = np.repeat(ks, ms)
        m_row = np.repeat(ms, ms)
        i = np.arange(1, len(owner) + 1) - np.repeat(np.cumsum(ms) - ms, ms)
        frac = i / (m_row + 1)
        at = dest[owner] - m_row + i - 1  # i-th of the m rows before input row k
        out: dict[str, npt.NDArray[np.float64]] = {}
        for r in ["t", *roles]:
            v = np.asarray(getattr(s, r), dtype=np.float64)
            pv = np.empty(n)
            pv[1:] = v[:-1]
            pv[0] = last[r] if last is not None and r in last else v[0]
            col = np.empty(total)
            col[dest] = v
            step = v - pv
            wrap = self.period if r == "position" else None
            if wrap is not None:
                step = np.mod(step + 0.5 * wrap, wrap) - 0.5 * wrap
            # v_i = v_(k-1) + (v_k - v_(k-1)) i / (m + 1), i = 1..m (modulo the wrap)
            vals = pv[owner] + step[owner] * frac
            if wrap is not None:
                vals = np.mod(vals, wrap)
            col[at] = vals
            out[r] = col
        return Signals.from_roles(out), real


# ------------------------------------------------------------------ a whole record
class FilledRecord:
    """A record with its gaps filled (:class:`GapFiller`), not kept: the rows
    ``c0:c1`` are filled again when sliced, from the measured samples around them
    (each filled gap depends only on the measured rows on its two sides, so the values
    are those of filling the whole record, bit for bit).

    ``real`` marks the measured rows (``None``: nothing filled, the record itself).
    """

    #: filled rows per entry of the table of measured rows before them
    STEP = 65536

    def __init__(self, signals: Signals | SpilledSignals, real: PackedMask | None,
                 policy: SamplePolicy) -> None:
        self.measured = signals
        self.real = real
        self.policy = policy
        self._n = len(signals) if real is None else len(real)
        if real is not None:
            # measured rows before filled row k * STEP
            self._before = np.concatenate(
                [[0], np.cumsum([real.count(a, a + self.STEP)
                                 for a in range(0, len(real), self.STEP)])]).astype(np.int64)

    def __len__(self) -> int:
        return self._n

    @property
    def position(self) -> ColumnLike | None:
        """The measured position (None without one): tells whether there is one."""
        return self.measured.position

    def _measured_before(self, c: int) -> int:
        """Measured rows before filled row ``c``."""
        assert self.real is not None
        k = c // self.STEP
        return int(self._before[k]) + self.real.count(k * self.STEP, c)

    def slice(self, c0: int, c1: int) -> Signals:
        """Filled rows ``c0:c1`` (a new block)."""
        if self.real is None:
            return self.measured.slice(c0, c1)
        c0, c1 = max(0, c0), min(self._n, c1)
        if c1 <= c0:
            return self.measured.slice(0, 0)
        real = self.real
        # the measured row at or before c0 (filled row p), through the one at or after
        # c1 - 1: every gap of c0:c1 with both its sides
        m_lo = self._measured_before(c0)
        if real[c0]:
            p, first = c0, m_lo
        else:
            p = c0 - 1
            while not real[p]:
                p -= 1
            first = m_lo - 1
        last = self._measured_before(c1) + (0 if real[c1 - 1] else 1)
        filled, _ = self.policy.filler().fill(self.measured.slice(first, last))
        return filled.slice(c0 - p, c1 - p)


@dataclass(frozen=True)
class SelectedSamples:
    """A record after :meth:`SamplePolicy.apply`, in the rows of the filled record.

    ``signals`` has the gaps filled (:class:`FilledRecord`: filled again where
    sliced); ``real`` marks the measured rows (``None``: nothing
    was filled, every row is real); ``restart`` the rows where the filter restarts;
    ``use`` the rows that update the estimators; ``usable`` the rows a selection may
    use: the measured rows outside the memory of a doubtful fill
    (:meth:`GapFiller.settling`; ``None``: every row). The masks are packed
    (:class:`~canrls.core.spill.PackedMask`: read them in slices; ``np.asarray`` unpacks).
    """

    signals: FilledRecord
    real: PackedMask | None
    restart: PackedMask
    use: PackedMask
    usable: PackedMask | None = None

    #: rows unpacked at a time where a whole mask is read
    BLOCK = 65536

    def segments(self) -> list[tuple[int, int]]:
        """``[start, stop)`` of each run of rows the filter goes through without a restart."""
        starts = [a + int(k) for a, r in self.restart.blocks(self.BLOCK)
                  for k in np.flatnonzero(r)]
        ends = starts[1:] + [len(self.restart)]
        return [(a, b) for a, b in zip(starts, ends, strict=True) if b > a]

    @overload
    def measured(self, a: PackedMask) -> npt.NDArray[np.bool_]: ...
    @overload
    def measured(self, a: npt.NDArray[_G]) -> npt.NDArray[_G]: ...

    def measured(self, a: npt.NDArray[_G] | PackedMask
                 ) -> npt.NDArray[_G] | npt.NDArray[np.bool_]:
        """The measured rows of ``a`` (rows of the filled record), block by block."""
        if self.real is None:
            return np.asarray(a)
        return np.concatenate([np.asarray(a[:0])]
                              + [np.asarray(a[c0:c0 + len(r)])[r]
                                 for c0, r in self.real.blocks(self.BLOCK)])

    def filled(self, mask: B | PackedMask) -> B | PackedMask:
        """A mask over the measured rows spread over the filled record (filled rows
        False): packed, unless nothing was filled (``mask`` itself)."""
        if self.real is None:
            return mask
        out = MaskPacker()
        m = 0
        for _, r in self.real.blocks(self.BLOCK):
            k = int(np.count_nonzero(r))
            part = np.zeros(len(r), np.bool_)
            part[r] = mask[m:m + k]
            out.append(part)
            m += k
        return out.mask()
