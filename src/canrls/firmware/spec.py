"""The whole estimator as the target runs it, in integers: the bit-exact specification.

:class:`TargetEstimator` takes the drive's CAN frames one at a time (ID, payload bytes,
receive time in ticks) and runs, for the integers of a
:class:`~canrls.firmware.target_model.TargetModel`, what
``src/canrls/c/firmware/canrls_target.c`` runs:
the same names, the same order of operations, each line with its equation beside it.
Python integers do not overflow; where the C needs a split or a bound to stay in
``int64_t``, :mod:`canrls.firmware.qmath` says how and the bound is built into the model.
The steps per frame (:meth:`TargetEstimator.frame`: decode, pair) and per sample
(:meth:`TargetEstimator.sample`: restart, filter, select, normalise, update, publish)
are listed in docs/target.md, *Per frame and per sample*.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from fractions import Fraction
from typing import Any

import numpy as np

from canrls.can.e2e import CRC8_TABLE
from canrls.estimation.fixed.estimator import FixedRLS
from canrls.firmware.qmath import (
    MASK32,
    MASK64,
    ONE_Q30,
    ceil_scaled,
    clog2,
    dyadic,
    exp_neg_q24,
    f32_bits,
    floor_scaled,
    isqrt,
    mul_rsh,
    rsh,
    sat,
    scale_p64,
    sincos_q64,
    tanh_q24,
)
from canrls.firmware.target_model import (
    SRC_CONST,
    SRC_COS,
    SRC_RAW,
    SRC_SIN,
    SRC_STRIBECK,
    SRC_TANH,
    W_FRAC,
    Column,
    EquationSpec,
    TargetModel,
)

__all__ = ["TargetEstimator", "EquationState", "REJECTS", "SAMPLE", "PUBLISH", "trace_max_float"]

#: what :meth:`TargetEstimator.frame` returns (bits)
SAMPLE, PUBLISH = 1, 2
#: the reasons a frame is rejected or dropped, in the order of the C counters
REJECTS = ("length", "crc", "repeated", "range", "unpaired", "duplicated", "restarts")
_I32 = (-(1 << 31), (1 << 31) - 1)
_I62 = 1 << 62


def _s32(x: int) -> int:
    """``x`` modulo 2^32 as a signed 32-bit difference (the C's ``(int32_t)(a - b)``)."""
    x &= MASK32
    return x - (1 << 32) if x >> 31 else x


def trace_max_float(T: int, plan: dict[str, int], cfg: Any, lam: float) -> float:
    """A ``trace_max`` [float] for which :class:`FixedRLS` builds ``trace_max_lam = T``."""
    lam_q = Fraction(cfg.lam.to_int(Fraction(lam)), 1 << cfg.lam.frac)
    ktr = lam_q * Fraction(2) ** (cfg.P.frac - plan["trace_ps"])
    return float((Fraction(T) + Fraction(1, 2)) / ktr)


@dataclass
class EquationState:
    """What one equation carries from sample to sample."""

    spec: EquationSpec
    rls: FixedRLS
    #: the multipliers' shifts now (they follow the exponents)
    sh: list[int]
    sh_y: int
    pending: list[bool]
    pending_y: bool
    #: the ridge weight of each column, m 2^e exactly, and its term of the trace bound
    ridge: list[tuple[int, int]]
    terms: list[int]
    #: warm-up samples left, and the last speed W (0 after a restart)
    left: int = 0
    w_last: int = 0
    updates: int = 0
    #: the residual's running mean square, eps format squared
    ms: int = 0
    rescales: int = 0
    #: flags of the kernel's steps since the last publication (OR)
    flags: int = 0
    exponents: list[int] = field(default_factory=list)


class TargetEstimator:
    """The per-frame and per-sample path of the target on ``model``'s integers."""

    def __init__(self, model: TargetModel) -> None:
        self.m = model
        nm = len(model.messages)
        self.last_counter = [-1] * nm
        self.rejects = dict.fromkeys(REJECTS, 0)
        # pairing: the open period
        self.open_mask = 0
        self.open_t = 0
        self.open_counter = -1
        self.raw = dict.fromkeys(model.roles, 0)
        self.all_mask = (1 << nm) - 1
        #: counters pair frames when every message has one, all of one width
        self.match_counters = model.match_counters
        # the sample clock
        self.has_t = False
        self.last_t = 0
        self.samples = 0
        # the filter bank: x1, x2 (state), up (previous input), primed
        nf = len(model.filters)
        self.x1 = [0] * nf
        self.x2 = [0] * nf
        self.up = [0] * nf
        self.primed = [False] * nf
        for i, f in enumerate(model.filters):
            if f.kind == SRC_CONST:
                # F[1] = 1 exactly, sF[1] = 0: the constant needs no filter
                self.x1[i], self.primed[i] = ONE_Q30 << f.fx, True
        self.eqs = [self._equation(e) for e in model.equations]
        self.since_publish = 0
        self.publications = 0
        self.frame_loss = False

    # ------------------------------------------------------------------ set-up
    def _equation(self, e: EquationSpec) -> EquationState:
        terms = list(e.trace_terms)
        rls = self._kernel(e, None, terms)
        return EquationState(
            spec=e, rls=rls, sh=[c.sh for c in e.columns], sh_y=e.output.sh,
            pending=[c.pending for c in e.columns], pending_y=e.output.pending,
            ridge=[dyadic(r) for r in e.ridge], terms=terms,
            exponents=[c.exponent for c in e.columns] + [e.output.exponent])

    def _trace_bound(self, e: EquationSpec, terms: Sequence[int]) -> int:
        """The plan's ``trace_max_lam``: the sum of the columns' terms (the prior's
        trace), at most the cap; or the configured bound."""
        return min(sum(terms), e.trace_cap) if e.trace_follows else e.plan["trace_max_lam"]

    def _kernel(self, e: EquationSpec, state: dict[str, Any] | None,
                terms: Sequence[int]) -> FixedRLS:
        """A kernel with the plan of ``terms`` (``canrls_init_q31``), continuing from
        ``state`` (``canrls_restore_q31``; counters and ``frozen`` kept) or from the prior."""
        T = self._trace_bound(e, terms)
        tm = trace_max_float(T, e.plan, e.config, e.lam) if e.trace_follows else None
        if state is None:
            rls = FixedRLS(e.config, e.n, lam=e.lam, alpha=[float(r) for r in e.ridge],
                           trace_max=tm if tm is not None else _plan_trace(e))
            st = rls.state()
            P = np.zeros((e.n, e.n), np.int64)
            P[np.diag_indices(e.n)] = e.p0
            st["P"], st["P_exp"] = P, e.e0
            rls = FixedRLS.from_state(st)
        else:
            st = dict(state)
            if tm is not None:
                st["trace_max"] = tm
            rls = FixedRLS.from_state(st)
        if rls.constants["trace_max_lam"] != T:  # pragma: no cover - guarded by the rule
            raise AssertionError(f"trace bound {rls.constants['trace_max_lam']} != {T}")
        return rls

    # ------------------------------------------------------------------ frames in
    def frame(self, frame_id: int, extended: bool, data: bytes, t: int) -> int:
        """One received frame (``t``: its receive time in ticks, modulo 2^32). Returns
        :data:`SAMPLE` when it completed a sample (processed), with :data:`PUBLISH` when
        a publication is due; 0 otherwise."""
        mi = -1
        for i, mm in enumerate(self.m.messages):
            if mm.id == frame_id and mm.extended == bool(extended):
                mi = i
                break
        if mi < 0:
            return 0
        msg = self.m.messages[mi]
        # length: the DBC's
        if len(data) != msg.dlc:
            self.rejects["length"] += 1
            self.frame_loss = True
            return 0
        # E2E CRC-8: over the ID (2 bytes, little endian), then bytes 1..dlc-1
        if msg.crc:
            c = 0xFF
            for b in (frame_id & 0xFF, (frame_id >> 8) & 0xFF, *data[1:]):
                c = int(CRC8_TABLE[c ^ b])
            if (c ^ 0xFF) != data[0]:
                self.rejects["crc"] += 1
                self.frame_loss = True
                return 0
        # alive counter: one equal to the last accepted is a repeat
        counter = -1
        if msg.counter is not None:
            counter = msg.counter.extract(data) or 0   # an integer field: never None
            if counter == self.last_counter[mi]:
                self.rejects["repeated"] += 1
                self.frame_loss = True
                return 0
            self.last_counter[mi] = counter
        # strict range of every mapped field (a float's NaN and infinity too)
        raws = {}
        for role, f in self.m.roles.items():
            if f.msg == mi:
                v = f.extract(data)
                if v is None or not f.lo <= v <= f.hi:
                    self.rejects["range"] += 1
                    self.frame_loss = True
                    return 0
                raws[role] = v
        return self._pair(mi, counter, raws, t & MASK32)

    def _pair(self, mi: int, counter: int, raws: dict[str, int], t: int) -> int:
        bit = 1 << mi
        key = counter if self.match_counters else -1
        if self.open_mask:
            same = _s32(t - self.open_t) <= self.m.tol_ticks and key == self.open_counter
            if same and self.open_mask & bit:
                # a second frame of this message in the period: dropped
                self.rejects["duplicated"] += 1
                self.frame_loss = True
                return 0
            if not same:
                # another period began: the open one stays incomplete
                self.rejects["unpaired"] += bin(self.open_mask).count("1")
                self.frame_loss = True
                self.open_mask = 0
        if not self.open_mask:
            self.open_t, self.open_counter = t, key
        self.open_mask |= bit
        self.raw.update(raws)
        if self.open_mask != self.all_mask:
            return 0
        self.open_mask = 0
        return self.sample(t)

    # ------------------------------------------------------------------ one sample
    def _inputs(self) -> list[int]:
        """The input ``u`` of every filter of the bank for this sample."""
        m = self.m
        raw = self.raw
        z = r = 0
        if m.tanh_arg is not None:
            mz, bz, sz = m.tanh_arg
            # z = w / band, Q24
            z = sat(rsh(raw["speed"] * mz + bz, sz), *_I32)
        if m.stribeck_arg is not None:
            mr, br, sr = m.stribeck_arg
            # r = w / ws, Q24
            r = sat(rsh(raw["speed"] * mr + br, sr), *_I32)
        ph = 0
        if m.phase is not None:
            # phase = raw PM + PO, turns in Q64 (modulo one turn)
            ph = (raw["position"] * m.phase[0] + m.phase[1]) & MASK64
        u = []
        for f in m.filters:
            if f.kind == SRC_RAW:
                u.append(raw[f.role])
            elif f.kind == SRC_TANH:
                # tanh(w / band)
                u.append(tanh_q24(z))
            elif f.kind == SRC_STRIBECK:
                # x = (w / ws)^2, Q24, at most 32 (exp(-32) is 0 in Q30)
                x = min(rsh(r * r, 24), 32 << 24)
                # tanh(w / band) exp(-(w / ws)^2)
                u.append(rsh(tanh_q24(z) * exp_neg_q24(x), 30))
            elif f.kind in (SRC_SIN, SRC_COS):
                # sin, cos of k theta: the phase times k, modulo one turn
                s, c = sincos_q64((f.order * ph) & MASK64)
                u.append(s if f.kind == SRC_SIN else c)
            else:
                u.append(0)  # the constant: no input
        return u

    def _filter(self, u: Sequence[int]) -> None:
        """Advance every filter of the bank by one sample."""
        a00, a01, a10, a11 = self.m.A
        for i, f in enumerate(self.m.filters):
            if f.kind == SRC_CONST:
                continue
            if not self.primed[i]:
                # at rest on the first sample: x = [u 2^FX, 0]
                self.x1[i], self.x2[i], self.up[i], self.primed[i] = u[i] << f.fx, 0, u[i], True
                continue
            g00, g02, g10, g12 = self.m.G[f.hold]
            x1, x2 = self.x1[i], self.x2[i]
            # x1 = A00 x1 + A01 x2 + (G0_1 u[k-1] + G1_1 u[k]) 2^FX, Q30 coefficients
            y1 = rsh(a00 * x1 + a01 * x2 + ((g00 * self.up[i] + g10 * u[i]) << f.fx), 30)
            # x2 = A10 x1 + A11 x2 + (G0_2 u[k-1] + G1_2 u[k]) 2^FX   (x2 = sF[u] T 2^FX)
            y2 = rsh(a10 * x1 + a11 * x2 + ((g02 * self.up[i] + g12 * u[i]) << f.fx), 30)
            if f.narrow:
                # 32-bit states (an input bounded by 1): saturated to int32
                y1, y2 = sat(y1, *_I32), sat(y2, *_I32)
            self.x1[i], self.x2[i], self.up[i] = y1, y2, u[i]

    def _state(self, c: Column) -> int:
        """``X + O`` of a column: the filter state it reads and its offset."""
        return (self.x2[c.filter] if c.derivative else self.x1[c.filter]) + c.offset

    def restart(self) -> None:
        """The filter bank starts again at rest, every equation's warm-up too."""
        for i, f in enumerate(self.m.filters):
            if f.kind != SRC_CONST:
                self.primed[i] = False
        for es in self.eqs:
            es.left, es.w_last = es.spec.selection.warmup, 0

    def sample(self, t: int) -> int:
        """One sample, complete in :attr:`raw` at time ``t`` (ticks)."""
        d = _s32(t - self.last_t)
        if not self.has_t or d < 0 or d > self.m.gap_ticks:
            # the first sample, time going back, or a period missing: restart
            if self.has_t:
                self.rejects["restarts"] += 1
            self.restart()
        self.has_t, self.last_t = True, t
        self._filter(self._inputs())
        # the speed of the selection: W = raw 2^16 + offset
        w = (self.raw["speed"] << W_FRAC) + self.m.w_offset
        for es in self.eqs:
            sel = es.spec.selection
            aw = -w if w < 0 else w
            out = aw < sel.min_w or (sel.max_w >= 0 and aw > sel.max_w) or (
                sel.cross and ((es.w_last < 0 < w) or (w < 0 < es.w_last)))
            if out:
                es.left = sel.warmup + 1
            es.w_last = w
            if es.left > 0:
                es.left -= 1
                continue
            self._update(es)
        self.samples += 1
        self.since_publish += 1
        if self.since_publish >= self.m.publish_every:
            self.since_publish = 0
            return 1 | 2
        return 1

    # ------------------------------------------------------------------ estimation
    def _values(self, es: EquationState) -> tuple[list[int], int]:
        """The columns and the output of a used sample in their formats (before the
        kernel's clamp): ``rsh((X + O) m, sh)``."""
        e = es.spec
        phi = [mul_rsh(self._state(c), c.m, es.sh[j]) for j, c in enumerate(e.columns)]
        y = mul_rsh(self._state(e.output), e.output.m, es.sh_y)
        return phi, y

    def _update(self, es: EquationState) -> None:
        e = es.spec
        phi, y = self._values(es)
        if self._changes(es, phi, y):
            self._adapt(es, phi, y)
            phi, y = self._values(es)
        step = es.rls.update(np.array([sat(v, *_I32) for v in phi], np.int64), sat(y, *_I32))
        es.updates += 1
        es.flags |= int(step.flags)
        # the residual's mean square: ms <- ms + (eps^2 - ms) >> rms_shift
        es.ms += (step.eps * step.eps - es.ms) >> e.rms_shift

    def _changes(self, es: EquationState, phi: Sequence[int], y: int) -> bool:
        """Whether this used sample changes the normalisation (``_next_change``)."""
        e = es.spec
        lim = 1 << e.f_phi
        for j, c in enumerate(e.columns):
            if es.pending[j]:
                if self._state(c) != 0:
                    return True
            elif c.adaptive and abs(phi[j]) > lim:
                return True
        if es.pending_y:
            return self._state(e.output) != 0
        return abs(y) > (1 << e.f_y)

    def _adapt(self, es: EquationState, phi: Sequence[int], y: int) -> None:
        r"""The exponents change before this sample (the pipeline's ``_adapt``):

        * a data-scaled column above full scale: ``d`` with the sample at most 1/4 of
          full scale, ``d = clog2(|X + O| |m|) - sh - f + 2``;
        * a pending column at its first value: ``d`` with it at most 1/16 of full scale
          (``+ 4``), and the prior of the calibration's rule at the top of the window's
          range (``alpha 2^-8``: ``P_jj`` a quarter of its rescaled word);
        * the output likewise, and it moves along where an estimate would leave half its
          bound (:math:`|\theta_j| 2^{d_j - d_y}` above ``theta_half``, rounded down to
          a power of two);
        * the kernel's state in the new units (:meth:`_rescale`); a column that grew
          takes the weakest prior of the start (:meth:`_raise_prior`).
        """
        e = es.spec
        n = e.n
        d = [0] * n
        first: list[int] = []
        for j, c in enumerate(e.columns):
            big = abs(self._state(c)) * abs(c.m)
            if es.pending[j]:
                if big:
                    # 16 |phi| <= 2^(f + d): the first value at most 1/16 of full scale
                    d[j] = clog2(big) - es.sh[j] - e.f_phi + 4
                    first.append(j)
            elif c.adaptive and abs(phi[j]) > (1 << e.f_phi):
                # 4 |phi| <= 2^(f + d)
                d[j] = clog2(big) - es.sh[j] - e.f_phi + 2
        big_y = abs(self._state(e.output)) * abs(e.output.m)
        first_y = False
        dy = 0
        if es.pending_y:
            if big_y:
                dy = clog2(big_y) - es.sh_y - e.f_y + 4
                first_y = True
        elif abs(y) > (1 << e.f_y):
            dy = clog2(big_y) - es.sh_y - e.f_y + 2
        # theta_j takes 2^(d_j - d_y): the output moves where an estimate would leave
        # half its bound, |theta_j| 2^(d_j - dy) <= 2^h 2^s
        h = clog2(e.theta_half + 1) - 1
        s = 0
        for j in range(n):
            w = abs(int(es.rls.theta[j]))
            if w:
                s = max(s, clog2(w) + d[j] - dy - h)
        dy += s
        self._rescale(es, d, dy, first)
        for j in range(n):
            if d[j] and not es.pending[j]:
                self._raise_prior(es, j, d[j])
            elif d[j] and es.pending[j]:
                # the ridge scales with the column (then set below)
                es.ridge[j] = (es.ridge[j][0], es.ridge[j][1] - 2 * d[j])
        for j in first:
            # the first value: the prior alpha 2^-8 (its P_jj set by _rescale)
            es.pending[j] = False
            es.ridge[j] = dyadic(e.first_ridge)
            es.terms[j] = e.first_term
        if first_y:
            es.pending_y = False
        for j in range(n):
            es.sh[j] += d[j]
            es.exponents[j] += d[j]
        es.sh_y += dy
        es.exponents[n] += dy
        es.rescales += 1
        if e.trace_follows:
            es.rls = self._kernel(e, es.rls.state(), es.terms)

    def _rescale(self, es: EquationState, d: Sequence[int], dy: int,
                 first: Sequence[int] = ()) -> None:
        """The kernel's state in the new units: ``theta_j 2^(d_j - d_y)`` (its 64 bits),
        ``P_jk 2^(d_j + d_k)`` (its 64 bits) with the block exponent lowered by twice the largest
        growth (of the columns not ``first``), so that no word grows; left shifts
        saturate (counted). A column seen for the first time (``first``) holds the prior
        alone, in any units: its ``P_jj`` becomes ``P_jj alpha_old / alpha_new = P_jj / 4``
        (``alpha 2^-10`` of a pending column to ``alpha 2^-8``), its row 0 as it was."""
        e = es.spec
        n = e.n
        st = es.rls.state()
        counts = np.asarray(st["counts"]).copy()
        th = np.asarray(st["theta"]).copy()
        fr = np.asarray(st["theta_frac"]).copy()
        lo, hi = e.theta_lo << 32, (e.theta_hi << 32) | MASK32
        for j in range(n):
            v = (int(th[j]) << 32) | int(fr[j])
            s = d[j] - dy
            if s >= 0:
                v <<= s
                if not lo <= v <= hi:
                    counts[7] += 1  # theta
                    v = sat(v, lo, hi)
            else:
                v = rsh(v, -s)
            th[j], fr[j] = v >> 32, v & MASK32
        dmax = max([0, *(d[j] for j in range(n) if j not in first)])
        ex = int(st["P_exp"])
        e_new = max(0, ex - 2 * dmax)
        P = np.asarray(st["P"]).copy()
        P_frac = np.asarray(st["P_frac"]).copy()
        for j in range(n):
            for k in range(j, n):
                # P_jj / 4 for a first value, else P_jk 2^(d_j + d_k), at e_new, in 64 bits
                s = e_new - ex - 2 if j == k and j in first else d[j] + d[k] + e_new - ex
                P[j, k], P_frac[j, k], clamped = scale_p64(int(P[j, k]), int(P_frac[j, k]), s,
                                                           e.P_lo, e.P_hi)
                counts[8] += clamped  # P
        st.update(theta=th, theta_frac=fr, P=P, P_frac=P_frac, P_exp=e_new, counts=counts)
        es.rls = FixedRLS.from_state(st)

    def _raise_prior(self, es: EquationState, j: int, dj: int) -> None:
        r"""Column ``j`` grew by ``2^dj``: its prior, rescaled, weighs :math:`2^{2 d_j}`
        less; it is raised to the weakest prior of the start, :math:`\delta = \alpha_f -
        \alpha_j 2^{-2 d_j}`, as one kernel update with the regressor
        :math:`\sqrt\delta\,e_j` and the output 0 (exact information :math:`\delta`,
        less the rounding of the root)."""
        e = es.spec
        m, ex = es.ridge[j]
        ex -= 2 * dj
        fm, fe = dyadic(e.prior_floor)
        # D = floor(alpha_f 2^(2 f)) - ceil(alpha_j 2^(2 f))
        D = floor_scaled(fm, fe + 2 * e.f_phi) - ceil_scaled(m, ex + 2 * e.f_phi)
        if D > 0:
            q = min(isqrt(D), e.phi_hi)
            if q:
                phi = np.zeros(e.n, np.int64)
                phi[j] = q
                es.rls.update(phi, 0)
            es.ridge[j] = (fm, fe)
            es.terms[j] = e.floor_term
        else:
            es.ridge[j] = (m, ex)
            # terms_j 2^(2 d_j), saturated (a column grows: d_j > 0)
            es.terms[j] = min(es.terms[j] << (2 * dj), _I62)

    # ------------------------------------------------------------------ frames out
    def publish(self) -> list[tuple[int, bytes]]:
        """The frames of one publication, ``(id, payload)``: RlsEstimate of every
        parameter (``FixedValue = theta 2^(s_y - s_j - f_theta)`` as float32, ``Valid``
        once its equation has updated), RlsParamInfo of every parameter on every tenth
        publication (the first included), RlsStatus (the first equation's residual RMS
        ``sqrt(ms) 2^(s_y - f_eps)`` and update count) and RlsHealth (the kernel's flags
        since the last publication, a rejected or dropped frame as ``FrameLoss``, the
        active effects; ``Divergence`` 0: the target has no float reference). Empty
        when the model has no frames."""
        out_f = self.m.out
        frames: list[tuple[int, bytes]] = []
        if out_f is None:
            return frames
        cnt = self.publications & 0xF
        est, info = out_f["RlsEstimate"], out_f["RlsParamInfo"]
        idx = 0
        for es in self.eqs:
            e = es.spec
            n = e.n
            for j in range(n):
                valid = es.updates > 0
                # FixedValue = theta_j 2^(s_y - s_j - f_theta), float32 from the integers
                bits = f32_bits(int(es.rls.theta[j]),
                                es.exponents[n] - es.exponents[j] - e.f_theta) if valid else 0
                frames.append((est.id, est.pack({"Index": idx, "Counter": cnt,
                                                 "Valid": int(valid), "FixedValue": bits})))
                idx += 1
        if self.publications % 10 == 0:
            for i, (eff, comp, order, eqi) in enumerate(self.m.param_info):
                frames.append((info.id, info.pack({"Index": i, "Count": idx, "EffectId": eff,
                                                   "Component": comp, "Order": order,
                                                   "Equation": eqi})))
        e0 = self.eqs[0]
        st = out_f["RlsStatus"]
        # ResidualRms = sqrt(ms) 2^(s_y - f_eps)
        rms = f32_bits(isqrt(e0.ms), e0.exponents[e0.spec.n] - e0.spec.f_eps)
        frames.append((st.id, st.pack({"ResidualRms": rms, "UpdateCount": e0.updates & MASK32})))
        flags = 0
        for es in self.eqs:
            flags |= es.flags
            es.flags = 0
        hl = out_f["RlsHealth"]
        frames.append((hl.id, hl.pack({
            "Windup": flags & 1, "LowExcitation": (flags >> 1) & 1,
            "Saturation": (flags >> 2) & 1, "FrameLoss": int(self.frame_loss),
            "Frozen": (flags >> 3) & 1, "Counter": cnt, "ActiveEffects": self.m.active_effects,
            "Divergence": 0})))
        self.frame_loss = False
        self.publications += 1
        return frames

    # ------------------------------------------------------------------ results
    def theta_si(self) -> list[float]:
        """Every parameter in SI (float, for people: ``theta 2^(s_y - s_j - f_theta)``)."""
        out = []
        for es in self.eqs:
            n = es.spec.n
            for j in range(n):
                out.append(math.ldexp(int(es.rls.theta[j]), es.exponents[n] - es.exponents[j]
                                      - es.spec.f_theta))
        return out

    def snapshot(self) -> dict[str, Any]:
        """The integer state of the estimator (what the test vectors compare)."""
        eqs = []
        for es in self.eqs:
            st = es.rls.state()
            n = es.spec.n
            P, P_frac = np.asarray(st["P"]), np.asarray(st["P_frac"])
            eqs.append({
                "theta": [int(v) for v in st["theta"]],
                "theta_frac": [int(v) for v in st["theta_frac"]],
                "P": [int(P[j, k]) for j in range(n) for k in range(j, n)],
                "P_frac": [int(P_frac[j, k]) for j in range(n) for k in range(j, n)],
                "e": int(st["P_exp"]), "c": int(st["P_scale"]),
                "counts": [int(v) for v in st["counts"]],
                "sh": list(es.sh) + [es.sh_y], "updates": es.updates, "ms": es.ms,
                "rescales": es.rescales})
        return {"samples": self.samples, "x1": list(self.x1), "x2": list(self.x2),
                "rejects": [self.rejects[k] for k in REJECTS], "equations": eqs}


def _plan_trace(e: EquationSpec) -> float:
    """The configured trace bound's float (a trace_max that does not follow the prior)."""
    return trace_max_float(e.plan["trace_max_lam"], e.plan, e.config, e.lam)
