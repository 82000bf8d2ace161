"""The record as the pipeline sees it: the samples, rows and filtered signals the
diagnosis works on.

:class:`RecordSamples` selects the samples with the pipeline's own
:class:`~canrls.estimation.selection.SamplePolicy`: the gaps of lost frames are filled,
the filter restarts where the pipeline restarts it, and the used rows are the rows the
pipeline uses. Everything is filtered on the filled record (the filter keeps its time
base, as in the pipeline) and handed out on the measured rows, the rows of the
pipeline's :class:`~canrls.estimation.pipeline.EquationBlock`, so the columns and used
masks of the diagnosis are the pipeline's, bit for bit.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import numpy.typing as npt

from canrls.core.samples import Signals
from canrls.core.spill import ColumnLike, MaskPacker, PackedMask, SpilledSignals, as_packed
from canrls.estimation.equation import Equation, PositionUnwrapper
from canrls.estimation.model import Model
from canrls.estimation.selection import SamplePolicy
from canrls.estimation.settings import EstimatorSettings
from canrls.estimation.svf import SVF, Hold, impulse_response

__all__ = ["BLOCK", "RecordSamples"]

F64 = npt.NDArray[np.float64]
B = npt.NDArray[np.bool_]

#: Rows filtered at a time where a pass over the record builds many columns.
BLOCK = 32768


class _FilterSource:
    """Filtered signals (or a residual) on the measured rows, computed block by block
    when read: the filter (or regressor builder) runs forward from the block last
    computed, or from the start of the block's segment when the block read lies before
    it. No state is kept per block (nothing grows with the record), and the statistics
    read the record in order, so a pass over it filters each block once. The values
    are those of one pass, bit for bit (the filter carries its state exactly); the last
    few blocks are cached."""

    CACHE = 4

    def __init__(self, ctx: RecordSamples, svf: Any, compute: Callable[[int, int], F64],
                 n: int) -> None:
        self.svf = svf
        self.compute = compute
        self.n = n
        #: (c0, c1, m0, m1): filled rows c0:c1 are measured rows m0:m1
        self.pieces: list[tuple[int, int, int, int]] = []
        #: the measured rows of the filled record (packed; None: all), sliced where read
        self.real = ctx.selected.real
        #: the first piece of each piece's segment
        self.first: list[int] = []
        seg_starts = {a for a, _ in ctx.segments()}
        for c0, c1, m0, m1, _ in ctx._pieces(svf):
            self.first.append(len(self.pieces) if c0 in seg_starts or not self.first
                              else self.first[-1])
            self.pieces.append((c0, c1, m0, m1))
        self.starts = np.array([p[2] for p in self.pieces], dtype=np.int64)
        self.cache: dict[int, F64] = {}
        self.pos: int | None = None  # the piece the builder last computed

    def _run(self, i: int) -> F64:
        c0, c1, _, _ = self.pieces[i]
        out = self.compute(c0, c1)
        if self.real is not None:
            out = out[self.real[c0:c1]]
        if len(self.cache) >= self.CACHE:
            del self.cache[next(iter(self.cache))]
        self.cache[i] = out
        return out

    def piece(self, i: int) -> F64:
        """The measured rows of piece ``i``, all columns."""
        if i in self.cache:
            return self.cache[i]
        j = self.first[i]
        if self.pos is not None and j <= self.pos < i:
            start = self.pos + 1  # forward from the block last computed
        else:
            self.svf.reset()
            start = j
        for k in range(start, i + 1):
            out = self._run(k)
        self.pos = i
        return out

    def rows(self, a: int, b: int, col: int) -> F64:
        """Column ``col`` on the measured rows ``a:b``."""
        out = np.empty(max(b - a, 0))
        start = a
        i = int(np.searchsorted(self.starts, a, side="right")) - 1
        while a < b:
            _, _, m0, m1 = self.pieces[i]
            e = min(b, m1)
            if e > a:
                out[a - start:e - start] = self.piece(i)[a - m0:e - m0, col]
                a = e
            i += 1
        return out

    def gather(self, idx: npt.NDArray[np.intp], col: int) -> F64:
        """Column ``col`` on the measured rows ``idx`` (sorted)."""
        out = np.empty(len(idx))
        for i, (_, _, m0, m1) in enumerate(self.pieces):
            lo, hi = np.searchsorted(idx, [m0, m1])
            if hi > lo:
                out[lo:hi] = self.piece(i)[idx[lo:hi] - m0, col]
        return out


class _PositionChain:
    """The position's unwrapper and filter, reset together (for :class:`_FilterSource`)."""

    def __init__(self, unw: PositionUnwrapper, svf: SVF) -> None:
        self.unw = unw
        self.svf = svf

    def reset(self) -> None:
        self.unw.reset()
        self.svf.reset()


class Filtered:
    """A filtered signal on the measured rows that is not kept: slices and sorted index
    arrays are computed block by block (:class:`_FilterSource`); anything else (a mask,
    ``np.asarray``) makes the whole array first."""

    def __init__(self, source: _FilterSource, col: int) -> None:
        self.source = source
        self.col = col

    def __len__(self) -> int:
        return self.source.n

    @property
    def shape(self) -> tuple[int]:
        return (self.source.n,)

    def __array__(self, dtype: Any = None, copy: bool | None = None) -> F64:
        a = self.source.rows(0, self.source.n, self.col)
        return a if dtype is None else a.astype(dtype)

    def __getitem__(self, key: Any) -> Any:
        if isinstance(key, slice):
            a, b, step = key.indices(self.source.n)
            if step == 1:
                return self.source.rows(a, max(a, b), self.col)
        elif (isinstance(key, np.ndarray) and key.dtype.kind in "iu" and key.ndim == 1
              and (len(key) < 2 or bool(np.all(key[1:] >= key[:-1])))):
            return self.source.gather(key, self.col)
        return np.asarray(self)[key]


class RecordSamples:
    """What both analyses (before and after) share: samples, restarts, filtered signals.

    Attributes (measured rows): ``signals`` (as given), ``speed``, ``acceleration``,
    ``current`` (through the filter; on a drive whose mechanical output is the torque it
    reports, that torque: :attr:`effort` names which, :attr:`effort_unit` its unit),
    ``position`` (unwrapped, filtered), ``angle``
    (phase of periodic terms, filtered) and ``angle_raw`` (unfiltered), ``None``
    without position. These are :class:`Filtered`: not kept, unwrapped and filtered
    again block by block when sliced (read them in slices or at sorted rows;
    ``np.asarray`` makes the whole array). ``selected`` holds the filled record
    (:class:`~canrls.estimation.selection.SelectedSamples`, itself filled again where
    read: :class:`~canrls.estimation.selection.FilledRecord`); the phase on the filled
    rows: :meth:`angle_filled_blocks`.
    """

    def __init__(self, model: Model, signals: Signals | SpilledSignals, dt: float,
                 settings: EstimatorSettings, max_order: int) -> None:
        self.signals = signals
        t = signals.t
        assert t is not None, "a spilled record has its times from its first row on"
        #: the receive times of the measured rows (``signals.t``)
        self.t: ColumnLike = t
        self.dt = dt
        self.settings = settings
        self.max_order = max_order
        self.axis = model.axis
        self.pitch = model.pitch
        # gap filling and restarts are the same for every equation of the model
        self.policy = SamplePolicy.for_equation(model.equations[0], dt, settings)
        self.selected = self.policy.apply(signals, BLOCK)
        filled = self.selected.signals
        self.speed_unit = "rad/s" if model.axis == "rotary" else "m/s"
        self.position_unit = "rad" if model.axis == "rotary" else "m"
        self.acc_unit = "rad/s²" if model.axis == "rotary" else "m/s²"
        self.per = "revolution" if model.axis == "rotary" else "pitch"
        held = model.held
        #: the drive's effort the residual is binned by: ``"current"`` or ``"torque"``
        self.effort = "torque" if model.output == "torque" else "current"
        self.effort_unit = ("A" if self.effort == "current" else
                            "N·m" if model.axis == "rotary" else "N")
        effort = self.effort
        hold: dict[str, Hold] = {r: ("zoh" if r in held else "foh")
                                 for r in ("speed", "position")}
        hold["current"] = "zoh" if effort in held else "foh"
        self.speed_hold = hold["speed"]
        self.position_hold = hold["position"]
        self.cutoff_hz, self.zeta = model.cutoff_hz, model.zeta
        # F[speed], sF[speed], F[current] and F[position] on the measured rows, computed
        # block by block when read (:class:`Filtered`): not kept
        svf = SVF(model.cutoff_hz, dt, model.zeta, (hold["speed"], hold["current"]))

        def speed_current(c0: int, c1: int) -> F64:
            fb = filled.slice(c0, c1)
            raw = np.column_stack([fb.speed, getattr(fb, effort)]).astype(np.float64)
            f, sf = svf.process(raw)
            return np.column_stack([f[:, 0], sf[:, 0], f[:, 1]])

        sc = _FilterSource(self, svf, speed_current, len(signals))
        self.speed: Filtered = Filtered(sc, 0)
        self.acceleration: Filtered = Filtered(sc, 1)
        self.current: Filtered = Filtered(sc, 2)
        # the unwrapped position (as the model unwraps it) and the phase of periodic terms:
        # not kept either, unwrapped again block by block when read (the unwrapper
        # runs forward with the filter)
        self.position: Filtered | None = None
        self.angle_raw: Filtered | None = None
        self.angle: Filtered | None = None
        #: the phase of periodic terms times this is the unwrapped position (1: rotary)
        self.angle_scale = 1.0
        if filled.position is not None:
            period = 2.0 * math.pi if model.axis == "rotary" else model.wrap
            k = 1.0 if model.axis == "rotary" else 2.0 * math.pi / model.pitch
            self.angle_scale = k
            self._period = period
            chain = _PositionChain(
                PositionUnwrapper(period),
                SVF(model.cutoff_hz, dt, model.zeta, hold["position"]))

            def position(c0: int, c1: int) -> F64:
                # F[position], k F[position] (the angle; k = 1 on a rotary axis) and
                # k position (the angle unfiltered)
                fb = filled.slice(c0, c1).position
                assert fb is not None
                pos = chain.unw.process(np.asarray(fb, dtype=np.float64))
                fp = chain.svf.process(pos.reshape(-1, 1))[0][:, 0]
                return np.column_stack([fp, fp if k == 1.0 else k * fp,
                                        pos if k == 1.0 else k * pos])

            ps = _FilterSource(self, chain, position, len(signals))
            self.position = Filtered(ps, 0)
            self.angle = Filtered(ps, 1)
            self.angle_raw = Filtered(ps, 2)
        self._h: dict[str, F64] = {}
        self._use: dict[tuple[int, float, float], PackedMask] = {}
        self._coh: dict[bytes, tuple[F64, float]] = {}

    def angle_filled_blocks(self) -> Iterator[tuple[int, int, F64]]:
        """(b0, b1, the phase of periodic terms on the filled rows ``b0:b1``) over the
        filled record in blocks of at most :data:`BLOCK` rows from each segment's start,
        the position unwrapped as the model unwraps it (restarted at each segment)."""
        assert self.angle_raw is not None
        filled = self.selected.signals
        unw = PositionUnwrapper(self._period)
        k = self.angle_scale
        for a, b in self.segments():
            unw.reset()
            for b0 in range(a, b, BLOCK):
                b1 = min(b, b0 + BLOCK)
                fp = filled.slice(b0, b1).position
                assert fp is not None
                pos = unw.process(np.asarray(fp, dtype=np.float64))
                yield b0, b1, pos if k == 1.0 else k * pos

    # -- rows ---------------------------------------------------------------------------
    def _pieces(self, svf: SVF) -> Iterator[tuple[int, int, int, int, B | None]]:
        """(c0, c1, m0, m1, real rows of c0:c1 or None) over the filled record in blocks
        of at most :data:`BLOCK` rows, ``svf`` reset at each segment: filled rows
        ``c0:c1`` are measured rows ``m0:m1``."""
        real = self.selected.real
        m = 0
        for a, b in self.segments():
            svf.reset()
            for c0 in range(a, b, BLOCK):
                c1 = min(b, c0 + BLOCK)
                if real is None:
                    yield c0, c1, c0, c1, None
                    continue
                rb = real[c0:c1]
                k = int(np.count_nonzero(rb))
                yield c0, c1, m, m + k, rb
                m += k

    def segments(self) -> list[tuple[int, int]]:
        """Runs of rows of the filled record without a filter restart."""
        return self.selected.segments()

    def spread(self, used: B | PackedMask) -> B | PackedMask:
        """A mask over the measured rows as a mask over the filled record (packed when
        rows were filled: read it in slices)."""
        return self.selected.filled(used)

    def _filled_use(self, policy: SamplePolicy) -> PackedMask:
        """The rows of the filled record ``policy`` uses (the pipeline's rule), packed."""
        key = (policy.warmup, policy.min_speed, policy.max_speed)
        if key not in self._use:
            # block by block over the filled record (the selector carries its state)
            filled = self.selected.signals
            usable = self.selected.usable  # measured, not in a doubtful fill's memory
            selector = policy.selector()
            use = MaskPacker()
            for c0 in range(0, len(filled), BLOCK):
                fb = filled.slice(c0, c0 + BLOCK)
                u = selector.select(fb.t, fb.speed).use
                use.append(u if usable is None else u & usable[c0:c0 + len(fb)])
            self._use[key] = use.mask()
        return self._use[key]

    def measured_mask(self, mask: PackedMask) -> PackedMask:
        """A mask over the filled record on the measured rows, packed, block by block
        (``mask`` itself when nothing was filled)."""
        real = self.selected.real
        if real is None:
            return mask
        out = MaskPacker()
        for c0, r in real.blocks(BLOCK):
            out.append(mask[c0:c0 + len(r)][r])
        return out.mask()

    def used(self, equation: Equation) -> PackedMask:
        """The measured rows the pipeline uses for ``equation`` (without the rows of a
        non-finite column, which the builder finds), packed."""
        policy = SamplePolicy.for_equation(equation, self.dt, self.settings)
        return self.measured_mask(self._filled_use(policy))

    def _keep_filled(self, order: int) -> PackedMask:
        return self._filled_use(self.policy.for_order(order))

    def keep(self, order: int) -> PackedMask:
        """Measured rows where a periodic column of ``order`` is sampled finely enough.

        The pipeline skips the samples where the fastest periodic column advances more
        than ``max_phase_step`` rad per sample (and the filter warm-up after them): the
        straight line between samples no longer follows ``sin(k theta)`` there, and near
        ``k omega dt = 2 pi`` the samples alias to low frequencies that pass the filter.
        A candidate periodic column is set to zero on the other rows (not the rows
        dropped: the other candidates are compared on the same samples).
        """
        return self.measured_mask(self._keep_filled(order))

    # -- filtered signals and columns -----------------------------------------------------
    def _mask_periodic(self, eq: Equation, first: int, phi: F64, a: int) -> None:
        """Zero candidate periodic columns (index >= ``first``) of the filled rows
        ``a:a+len(phi)`` where :meth:`keep` says so."""
        for j in range(first, eq.n):
            k = eq.parameters[j].order
            if k > 0:
                keep = self._keep_filled(k)[a:a + len(phi)]
                if not keep.all():
                    phi[~keep, j] = 0.0

    def columns(self, eq: Equation, first: int | None = None) -> tuple[F64, F64]:
        """(phi, y) of an equation on the measured rows (normalised), as the pipeline
        builds them (gaps filled, restarts); periodic columns from ``first`` on (default:
        none) zeroed where :meth:`keep` says so."""
        builder = eq.builder(self.dt)
        filled = self.selected.signals
        n = len(filled)
        phi = np.empty((n, eq.n))
        y = np.empty(n)
        for a, b in self.segments():
            builder.reset()
            rb = builder.process(filled.slice(a, b))
            phi[a:b] = rb.phi
            y[a:b] = rb.y
        self._mask_periodic(eq, eq.n if first is None else first, phi, 0)
        return self.selected.measured(phi), self.selected.measured(y)

    def gram(self, eq: Equation, used: B | PackedMask, first: int) -> F64:
        """Gram matrix of [phi, y] over the ``used`` measured rows, block by block
        (periodic columns from ``first`` on masked as in :meth:`columns`)."""
        builder = eq.builder(self.dt)
        filled = self.selected.signals
        used_f = self.spread(used)
        m = eq.n + 1
        A = np.zeros((m, m))
        for a, b in self.segments():
            builder.reset()
            for c0 in range(a, b, BLOCK):
                c1 = min(b, c0 + BLOCK)
                rb = builder.process(filled.slice(c0, c1))
                phi = rb.phi
                self._mask_periodic(eq, first, phi, c0)
                u = used_f[c0:c1]
                Z = np.column_stack([phi[u], rb.y[u]])
                A += Z.T @ Z
        return A

    def _blocks(self, eq: Equation) -> Iterator[tuple[int, F64, F64, B | None]]:
        """(first filled row, phi, y, measured rows or None: all) of an equation, block
        by block over the filled record (the filter restarted at each segment), no
        periodic column masked: :meth:`columns` in pieces of at most :data:`BLOCK` rows."""
        builder = eq.builder(self.dt)
        filled = self.selected.signals
        real = self.selected.real
        for a, b in self.segments():
            builder.reset()
            for c0 in range(a, b, BLOCK):
                c1 = min(b, c0 + BLOCK)
                rb = builder.process(filled.slice(c0, c1))
                yield c0, rb.phi, rb.y, None if real is None else real[c0:c1]

    def measured_blocks(self, eq: Equation) -> Iterator[tuple[int, F64, F64]]:
        """(first measured row, phi, y) of an equation on the measured rows, block by
        block (at most :data:`BLOCK` filled rows each, the filter restarted at each
        segment, no periodic column masked): the pipeline's columns, bit for bit,
        without the record's whole ``Phi``."""
        m = 0
        for _, phi, y, real in self._blocks(eq):
            if real is not None:
                phi, y = phi[real], y[real]
            yield m, phi, y
            m += len(y)

    def residual(self, eq: Equation, theta: npt.NDArray[np.floating[Any]]) -> Filtered:
        """``r = y - Phi theta`` on every measured row, in the output unit (``theta``
        normalised): not kept, computed block by block from the equation's columns
        when read (:class:`Filtered`: the builder runs forward block by block)."""
        builder = eq.builder(self.dt)
        filled = self.selected.signals
        real = self.selected.real

        def compute(c0: int, c1: int) -> F64:
            rb = builder.process(filled.slice(c0, c1))
            phi, y = rb.phi, rb.y
            out = np.empty((c1 - c0, 1))
            if real is None:
                out[:, 0] = eq.output_to_physical(y - phi @ theta)
            else:
                # on the measured rows only, as the pipeline's rows are
                rr = real[c0:c1]
                out[rr, 0] = eq.output_to_physical(y[rr] - phi[rr] @ theta)
            return out

        return Filtered(_FilterSource(self, builder, compute, len(self.signals)), 0)

    def output_at(self, eq: Equation, rows: npt.NDArray[np.intp]) -> F64:
        """The output ``y`` of an equation on the measured ``rows`` (sorted), in the
        output unit (as the pipeline's :class:`~canrls.estimation.pipeline.EquationBlock`
        holds it)."""
        out = np.empty(len(rows))
        for m, _, y in self.measured_blocks(eq):
            a, b = np.searchsorted(rows, [m, m + len(y)])
            out[a:b] = y[rows[a:b] - m]
        return eq.output_to_physical(out)

    def mean_square(self, eq: Equation, theta: F64, rows: B | PackedMask) -> float:
        """Mean square of ``r = y - Phi theta`` (output unit) over the measured
        ``rows``, block by block: nothing record-long."""
        s = 0.0
        for m, phi, y in self.measured_blocks(eq):
            u = rows[m:m + len(y)]
            if u.any():
                r = eq.output_to_physical(y[u] - phi[u] @ theta)
                s += float(np.dot(r, r))
        return s / max(int(rows.sum()), 1)  # PackedMask.sum counts block by block

    def fit_residual(self, eq: Equation, rows: B | PackedMask) -> Filtered:
        """Least-squares fit of ``eq`` on the measured ``rows`` and its residual on every
        measured row, in the output unit: ``r = y - Phi theta``, ``theta`` the
        minimum-norm least-squares solution of ``Phi[rows] theta = y[rows]``, without the
        record's ``Phi`` or its rows: ``[Phi y]`` is reduced block by block to a
        triangular factor (``R`` of a QR decomposition, the previous one stacked on each
        block), and ``R theta = Q'y`` solved with ``lstsq`` (the same singular values as
        ``Phi[rows]``, so the same rank and solution, to rounding)."""
        m = eq.n + 1
        Rz = np.zeros((0, m))
        n_rows = 0
        for m0, phi, y in self.measured_blocks(eq):
            sel = rows[m0:m0 + len(y)]
            if not sel.any():
                continue
            n_rows += int(np.count_nonzero(sel))
            # [R_prev z_prev; Phi_b y_b] = Q [R z]
            stacked = np.vstack([Rz, np.column_stack([phi[sel], y[sel]])])
            # numpy's stubs give every mode a QRResult: mode "r" returns R alone
            Rz = np.linalg.qr(stacked, mode="r")  # type: ignore[assignment]
        if len(Rz) < eq.n:
            Rz = np.vstack([Rz, np.zeros((eq.n - len(Rz), m))])
        # the rank cut-off lstsq takes for Phi[rows] (eps x its larger dimension)
        rcond = np.finfo(np.float64).eps * max(n_rows, eq.n)
        theta = np.linalg.lstsq(Rz[:eq.n, :eq.n], Rz[:eq.n, eq.n], rcond=rcond)[0]
        return self.residual(eq, theta)

    def impulse(self, hold: Hold, derivative: bool = False) -> F64:
        """Impulse response of F (DC gain 1), or of sF, for a hold, long enough to decay."""
        key = hold + ("/s" if derivative else "")
        if key not in self._h:
            self._h[hold], self._h[hold + "/s"] = impulse_response(
                self.cutoff_hz, self.dt, self.zeta, hold)
        return self._h[key]

    def coherence(self, order: int, used: B | PackedMask) -> tuple[float, float]:
        r"""How much a periodic column of ``order`` looks like a sinusoid in time.

        :math:`c_k = |\overline{e^{ik(\vartheta - \bar\omega t)}}|` with
        :math:`\bar\omega` the least-squares slope of the angle against time: 1 when the
        axis turns at a constant speed (order ``k`` in position is then the frequency
        :math:`k\bar\omega/2\pi` in time), near 0 when the speed varies. Returns
        ``(c_k, frequency [Hz])``.
        """
        assert self.angle_raw is not None
        key = as_packed(used).digest()  # block by block
        if key not in self._coh:
            # block by block: the means of t and the angle, the slope from the centred
            # sums, then the mean of exp(ik(a - w t)) per order (nothing record-long)
            ang, t = self.angle_raw, self.t
            n = int(used.sum())
            c = np.ones(self.max_order + 1)
            w = 0.0
            if n >= 3:
                def rows() -> Iterator[tuple[F64, F64]]:
                    for b0 in range(0, len(used), BLOCK):
                        u = used[b0:b0 + BLOCK]
                        yield ang[b0:b0 + BLOCK][u], t[b0:b0 + BLOCK][u]

                st = sa = 0.0
                for a, tt in rows():
                    st += float(np.sum(tt))
                    sa += float(np.sum(a))
                t_mean, a_mean = st / n, sa / n
                den = num = 0.0
                for a, tt in rows():
                    tc = tt - t_mean
                    den += float(np.dot(tc, tc))
                    num += float(np.dot(tc, a - a_mean))
                w = num / den if den > 0 else 0.0
                z = np.zeros(self.max_order + 1, np.complex128)
                for a, tt in rows():
                    z1 = np.exp(1j * (a - w * tt))
                    zk = np.ones_like(z1)
                    for k in range(1, self.max_order + 1):
                        zk *= z1
                        z[k] += complex(np.sum(zk))
                c[1:] = np.abs(z[1:] / n)
            self._coh[key] = (c, w)
        c, w = self._coh[key]
        cc = float(c[order]) if order < len(c) else 0.0
        return cc, abs(order * w) / (2 * math.pi)
