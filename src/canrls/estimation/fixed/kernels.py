r"""The fixed-point recursive least squares as specified, and its independent reference (private).

:class:`canrls.estimation.fixed.estimator.FixedRLS` owns the state, validates every argument and
derives the integer constants of the kernel (the *plan*, an ``int64`` vector indexed by
the ``I_*`` constants of :mod:`canrls.estimation.fixed.layout`). This module states the
recursion that runs on them, in place, on preallocated ``int64`` arrays, twice:

* :func:`fixed_block` (and the Q primitives :func:`round_shift`, :func:`saturate`,
  :func:`store`, :func:`sat_mul`, :func:`sat_add`, :func:`div_trunc`): the specification
  compiled for the host (C, ``canrls._fixedspec``, ``src/canrls/c/host/fixed_spec.c``), every
  update form and any ``n``;
* :func:`reference_block`: the same recursion in plain Python integers, written
  independently (unbounded integers, floor division instead of shifts, no shared
  helpers) and slow; the tests hold both compiled kernels to it, integer for integer.

The integer operations, the scaled covariance, the saturation sites and the step per
sample are in docs/fixed_point.md, *The specification in detail*.
"""

from __future__ import annotations

import numpy as np

from canrls import _fixedspec
from canrls._fixedspec import div_trunc, round_shift, sat_add, sat_mul, saturate, store

__all__ = ["round_shift", "saturate", "store", "sat_mul", "sat_add", "div_trunc", "fixed_block",
           "reference_block"]

from canrls.estimation.fixed.layout import (  # noqa: F401 - the layout, re-exported
    FLAG_FROZEN,
    FLAG_LOW_EXCITATION,
    FLAG_SATURATION,
    FLAG_WINDUP,
    I_C_S,
    I_CMP_DF,
    I_DEN_HI,
    I_DEN_LO,
    I_DIVIDEND,
    I_E_MAX,
    I_EPS_HI,
    I_EPS_LO,
    I_EPS_OS,
    I_EPS_TS,
    I_G_HI,
    I_G_LO,
    I_G_UP,
    I_GC_S,
    I_H_HI,
    I_H_LO,
    I_H_OS,
    I_HC_S,
    I_INV_LAM,
    I_K_HI,
    I_K_LO,
    I_KG_BL,
    I_KG_MAX,
    I_L_HI,
    I_L_LO,
    I_LAM_D,
    I_LHS_PS,
    I_ONE_D,
    I_ONE_L,
    I_P_HI,
    I_P_LO,
    I_P_S,
    I_PHI_HI,
    I_PHI_LO,
    I_PHI_PS,
    I_S_OS,
    I_SC_S,
    I_TC_S,
    I_TH_HI,
    I_TH_LO,
    I_TH_S,
    I_TMAX,
    I_TMAX_LIM,
    I_TR_HI,
    I_TR_PS,
    I_VW_PS,
    I_Y_HI,
    I_Y_LO,
    MODE_LITERAL,
    MODE_NAIVE,
    MODE_SYMMETRIC,
    NPARAM,
    NSITES,
    S_ACC,
    S_DEN,
    S_DIV,
    S_EPS,
    S_H,
    S_K,
    S_P,
    S_PHI,
    S_TH,
    S_Y,
    SITES,
)


# -------------------------------------------------------------------- kernel
def fixed_block(
    Phi: np.ndarray,
    Y: np.ndarray,
    theta: np.ndarray,
    theta_frac: np.ndarray,
    P: np.ndarray,
    P_frac: np.ndarray,
    scale: np.ndarray,
    work: np.ndarray,
    counts: np.ndarray,
    prm: np.ndarray,
    mode: int,
    frozen: bool,
    record: bool,
    eps_out: np.ndarray,
    theta_out: np.ndarray,
    trace_out: np.ndarray,
    exp_out: np.ndarray,
    flags_out: np.ndarray,
) -> int:
    r"""Run the fixed-point recursion over the rows of ``Phi``, in place (the compiled
    specification, ``canrls._fixedspec``).

    Parameters
    ----------
    Phi : ndarray of int64, shape (N, n), C-contiguous
        Regressor rows in the ``phi`` Q format (saturated to it here, counted).
    Y : ndarray of int64, shape (N,)
        Targets in the ``y`` Q format (saturated to it here, counted).
    theta : ndarray of int64, shape (n,)
        Estimate in the ``theta`` format, updated in place.
    theta_frac : ndarray of int64, shape (n,)
        The fraction of each estimate below its LSB, in units of :math:`2^{-32}` LSB
        (``0 <= theta_frac < 2**32``), updated in place: the estimate is the 64-bit
        ``theta * 2**32 + theta_frac``, of which ``theta`` is the published word
        (docs/fixed_point.md, *The estimate in 64 bits*).
    P : ndarray of int64, shape (n, n)
        The words :math:`\tilde P`, updated in place. ``MODE_SYMMETRIC`` reads and
        writes the upper triangle only (the lower one is never touched).
    P_frac : ndarray of int64, shape (n, n)
        The fraction of each word of ``P`` in units of :math:`2^{-32}` LSB, in
        :math:`[-2^{31}, 2^{31})`, updated in place (the same triangle): :math:`\tilde P`
        is the 64-bit ``P * 2**32 + P_frac``, of which ``P`` is the word rounded half up
        (docs/fixed_point.md, *The estimate and the covariance in 64 bits*).
    scale : ndarray of int64, shape (2,)
        ``[e, c]``: block exponent and forgetting scale (docs/fixed_point.md, *Scaled P*),
        updated in place.
    work : ndarray of int64, shape (6, n)
        Scratch rows: ``phi`` (saturated input), ``phi >> ps`` (the guard shift),
        ``h~``, ``w~``, ``K`` and an accumulator row. On return ``work[4]`` holds the
        gain of the last row (zeros when it was not applied).
    counts : ndarray of int64, shape (NSITES,)
        Saturation counters, incremented in place.
    prm : ndarray of int64, shape (NPARAM,)
        The plan (``I_*`` layout), built by :class:`canrls.estimation.fixed.estimator.FixedRLS`.
    mode : int
        ``MODE_SYMMETRIC``, ``MODE_LITERAL`` or ``MODE_NAIVE``.
    frozen : bool
        Compute :math:`\varepsilon` only; ``theta``, ``P`` and ``scale`` stay untouched.
    record : bool
        Write ``theta`` after each row into ``theta_out`` (shape (N, n)).
    eps_out : ndarray of int64, shape (N,)
        A-priori error (``eps`` format) of each row.
    trace_out, exp_out : ndarray of int64, shape (N,)
        :math:`\mathrm{tr}P\,2^{f_P - ps_{tr} + e}` (rounded) and ``e`` after each row.
    flags_out : ndarray of uint8, shape (N,)
        ``FLAG_*`` bits of each row.

    Returns
    -------
    int
        Number of rows that updated the state.
    """
    return _fixedspec.fixed_block(Phi, Y, theta, theta_frac, P, P_frac, scale, work, counts,
                                  prm, mode, frozen, record, eps_out, theta_out, trace_out,
                                  exp_out, flags_out)


# ------------------------------------------------------ pure-Python reference
class _Reference:
    """The arithmetic and the steps of :func:`reference_block` on one state: plain Python
    integers, every accumulator value checked against ``acc_bits``."""

    def __init__(self, P: list[list[int]], P_frac: list[list[int]], counts: list[int],
                 prm: list[int], acc_bits: int, mode: int) -> None:
        self.P, self.Pf, self.counts, self.p, self.mode = P, P_frac, counts, prm, mode
        self.n = len(P)
        self.acc_bits = acc_bits
        self.lim = 1 << (acc_bits - 1)
        p = prm
        # the 64-bit P: V = P~ 2^32 (units of 2^-32 LSB), held as the word rsh(V, 32) (P~
        # rounded half up) and the fraction V - word 2^32 in [-2^31, 2^31); V's range is
        # the word's, [lo - 1/2, hi + 1/2) LSB
        self.V_lo = (p[I_P_LO] << 32) - (1 << 31)
        self.V_hi = (p[I_P_HI] << 32) + (1 << 31) - 1

    # -- the arithmetic
    def chk(self, a: int) -> int:
        # an accumulator value must fit in acc_bits (the guard-bit argument)
        assert -self.lim <= a < self.lim, f"accumulator {a} outside {self.acc_bits} bits"
        return a

    @staticmethod
    def mul(a: int, b: int) -> int:
        # product of two words: exact, and within the 64-bit product register
        assert abs(a) <= (1 << 32) and abs(b) <= (1 << 32), "operand wider than a word"
        x = a * b
        assert abs(x) < (1 << 63)
        return x

    @staticmethod
    def rsh(x: int, s: int) -> int:
        # x / 2^s rounded half up: floor(x / 2^s + 1/2)
        assert 0 <= s <= 62
        return (x + (1 << (s - 1))) // (1 << s) if s > 0 else x

    def sat(self, x: int, lo: int, hi: int, site: int | None) -> int:
        if x > hi or x < lo:
            if site is not None:
                self.counts[site] += 1
            return hi if x > hi else lo
        return x

    def put(self, a: int, s: int, lo: int, hi: int, site: int) -> int:
        # store an accumulator into a word: rounding half up (s > 0) or exact left shift
        self.chk(a)
        if s > 0:
            self.chk(a + (1 << (s - 1)))
            return self.sat(self.rsh(a, s), lo, hi, site)
        return self.sat(a * (1 << -s), lo, hi, site)

    def Pget(self, i: int, j: int) -> int:
        # symmetric form: only the upper triangle exists
        if self.mode == MODE_SYMMETRIC and i > j:
            return self.P[j][i]
        return self.P[i][j]

    def Vget(self, i: int, j: int) -> int:
        # V = P~ 2^32: the word and its fraction
        return self.P[i][j] * (1 << 32) + self.Pf[i][j]

    def Vput(self, i: int, j: int, v: int) -> None:
        # V clamped to the word's range (counted), then split: word = rsh(V, 32)
        if v > self.V_hi or v < self.V_lo:
            self.counts[S_P] += 1
            v = self.V_hi if v > self.V_hi else self.V_lo
        self.P[i][j] = self.rsh(v, 32)
        self.Pf[i][j] = v - self.P[i][j] * (1 << 32)

    def stored(self) -> list[tuple[int, int]]:
        """The ``(i, j)`` of the stored words: the upper triangle, or all (literal, naive)."""
        n = self.n
        return [(i, j) for i in range(n)
                for j in range(i if self.mode == MODE_SYMMETRIC else 0, n)]

    # -- the steps of one row
    def inputs(self, row: list[int], y_raw: int) -> tuple[list[int], int]:
        """``phi >> ps`` and ``y``, each saturated to its format (counted)."""
        p = self.p
        phi = [self.sat(int(x), p[I_PHI_LO], p[I_PHI_HI], S_PHI) for x in row]
        y = self.sat(int(y_raw), p[I_Y_LO], p[I_Y_HI], S_Y)
        return [self.rsh(x, p[I_PHI_PS]) for x in phi], y

    def error(self, phg: list[int], y: int, theta: list[int]) -> int:
        """The a-priori error in the ``eps`` format."""
        p, chk = self.p, self.chk
        # eps = y - phi' theta
        a = chk(y * (1 << p[I_EPS_TS]) if p[I_EPS_TS] >= 0 else self.rsh(y, -p[I_EPS_TS]))
        for j in range(self.n):
            a = chk(a - self.mul(phg[j], theta[j]))
        return self.put(a, p[I_EPS_OS], p[I_EPS_LO], p[I_EPS_HI], S_EPS)

    def products(self, phg: list[int]) -> tuple[list[int], list[int]]:
        """``h~ = P~ phi`` and ``w~ = P~' phi`` (the same vector unless literal)."""
        p, n, chk, mul = self.p, self.n, self.chk, self.mul
        h: list[int] = []
        w: list[int] = []
        for i in range(n):
            a = 0
            for j in range(n):
                a = chk(a + mul(self.Pget(i, j), phg[j]))
            h.append(self.put(a, p[I_H_OS], p[I_H_LO], p[I_H_HI], S_H))
        if self.mode != MODE_LITERAL:
            w = list(h)
        else:
            for i in range(n):
                a = 0
                for j in range(n):
                    a = chk(a + mul(self.Pget(j, i), phg[j]))
                w.append(self.put(a, p[I_H_OS], p[I_H_LO], p[I_H_HI], S_H))
        return h, w

    def denominator(self, phg: list[int], h: list[int], e: int, c: int) -> int:
        """``s = c s~``, ``s~ = phi' h~`` at lambda's scale."""
        p, chk, rsh = self.p, self.chk, self.rsh
        # s~ = phi' h~ at lambda's scale ; s = c s~
        a = 0
        for i in range(self.n):
            a = chk(a + self.mul(phg[i], h[i]))
        if e > 0:
            chk(a + (1 << (e - 1)))
        st = self.put(rsh(a, e), p[I_S_OS], p[I_DEN_LO], p[I_DEN_HI], S_DEN)
        return self.sat(rsh(self.mul(st, c), p[I_SC_S]), p[I_DEN_LO], p[I_DEN_HI], S_DEN)

    def forgetting(self, h: list[int], w: list[int], sv: int, e: int,
                   c: int) -> tuple[int, int]:
        """``(lambda_k, flag)``: 1 and ``FLAG_WINDUP`` when the trace bound holds the
        forgetting, else lambda and 0."""
        p, n, chk, mul, rsh = self.p, self.n, self.chk, self.mul, self.rsh
        # windup <=> (c tr P~ - lambda trace_max) (lambda + s) > h' w
        lam_k = p[I_LAM_D]
        flag = 0
        if p[I_TMAX] <= (p[I_TMAX_LIM] >> e):
            trw = 0
            for i in range(n):
                trw = chk(trw + rsh(self.P[i][i], p[I_TR_PS]))
            T = chk(rsh(mul(trw, c), p[I_TC_S]) - p[I_TMAX] * (1 << e))
            if T > 0:
                d_lam = self.sat(lam_k + sv, p[I_DEN_LO], p[I_DEN_HI], None)
                a_vw = 0
                for i in range(n):
                    hi_ = rsh(mul(h[i], c), p[I_HC_S])
                    wi_ = rsh(mul(w[i], c), p[I_HC_S])
                    a_vw = chk(a_vw + rsh(mul(hi_, wi_), p[I_VW_PS]))
                lhs = chk(rsh(mul(min(T, p[I_P_HI]), d_lam), p[I_LHS_PS]))
                df = p[I_CMP_DF] - e
                if df >= 0:
                    up = lhs // (1 << min(df, 63)) > a_vw
                else:
                    up = lhs > a_vw // (1 << min(-df, 63))
                if up:
                    lam_k = p[I_ONE_D]
                    flag = FLAG_WINDUP
        return lam_k, flag

    def gain(self, lam_k: int, sv: int, e: int, c: int) -> tuple[int, int]:
        """``(g c, kg)``: the normalised reciprocal of ``d = lambda_k + s``, scaled by c."""
        p, sat = self.p, self.sat
        # d = lambda_k + s ; g = 1/d (C division, both operands positive), normalised:
        # g 2^kg = DIVIDEND 2^kg // d keeps the bits of g when d is large (kg = 0 for
        # d < 2^KG_BL, i.e. d < 2 in the steady state)
        d = sat(lam_k + sv, p[I_DEN_LO], p[I_DEN_HI], S_DEN)
        kg = 0
        if d <= 0:
            g = p[I_G_HI]
            self.counts[S_DIV] += 1
        else:
            kg = max(0, min(d.bit_length() - p[I_KG_BL], p[I_KG_MAX],
                            62 - p[I_P_S] - e, 62 - p[I_TH_S] - e))
            g = sat(p[I_DIVIDEND] * (1 << kg) // d, p[I_G_LO], p[I_G_HI], S_DIV)
        gc = sat(self.rsh(self.mul(g, c), p[I_GC_S]), p[I_G_LO], p[I_G_HI], S_DIV)
        return gc, kg

    def update(self, theta: list[int], tf: list[int], h: list[int], w: list[int],
               eps: int, gc: int, kg: int, e: int) -> int:
        """``theta += K eps`` and ``P~ -= K w~'``; ``FLAG_LOW_EXCITATION`` when the
        decrement of every diagonal word is zero, else 0."""
        p, n, mul, rsh = self.p, self.n, self.mul, self.rsh

        # normalisation: h~, w~ and eps shifted left to 31 bits (k, ke)
        def norm(m: int) -> int:
            assert 0 <= m < (1 << 31)
            return max(30 - m.bit_length(), 0)

        m = 0
        for x in h + w:
            m |= x if x >= 0 else -x - 1
        e0 = e
        k = min(norm(m), (62 - p[I_P_S] - e0 - kg) // 2, 62 - p[I_TH_S] - e0 - kg)
        ke = min(norm(eps if eps >= 0 else -eps - 1), 62 - p[I_TH_S] - e0 - k - kg)
        hs = [x * (1 << k) for x in h]
        ws = [x * (1 << k) for x in w]
        gcn = gc * (1 << p[I_G_UP])
        assert all(-(1 << 31) <= x < (1 << 31) for x in hs + ws) and 0 <= gcn < (1 << 31)
        # K = (g c) h~: the high word of the product, rounded half up
        K = [rsh(mul(hs[i], gcn), 32) for i in range(n)]
        # theta 2^32 + tf <- theta 2^32 + tf + floor(K eps 2^32)   (the 64-bit estimate)
        for i in range(n):
            ts = p[I_TH_S] + e + k + ke + kg
            u = mul(K[i], eps * (1 << ke))
            if ts >= 32:
                u = u // (1 << 32) * (1 << 32)  # the high word of the product (s >= 32)
            x = theta[i] * (1 << 32) + tf[i] + u * (1 << 32) // (1 << ts)
            top = p[I_TH_HI] * (1 << 32) + (1 << 32) - 1
            bot = p[I_TH_LO] * (1 << 32)
            if x > top or x < bot:
                self.counts[S_TH] += 1
                x = top if x > top else bot
            theta[i], tf[i] = x >> 32, x & ((1 << 32) - 1)
        # P~ <- P~ - K w~'   (upper triangle, or the full matrix for literal), at 2^-32
        # LSB: V -= u, u = K_i w~_j 2^(32 - ps) exactly for ps < 32, else the product's
        # high word rounded half up, rsh(K_i w~_j, 32) 2^(64 - ps)
        ps = p[I_P_S] + e + 2 * k + kg

        def dec(x: int) -> int:
            if ps < 32:
                return x * (1 << (32 - ps))
            return rsh(x, 32) * (1 << (64 - ps))

        low = all(dec(mul(K[i], ws[i])) == 0 for i in range(n))
        for i, j in self.stored():
            self.Vput(i, j, self.Vget(i, j) - dec(mul(K[i], ws[j])))
        return FLAG_LOW_EXCITATION if low else 0

    def forget(self, e: int, c: int, windup: bool) -> tuple[int, int]:
        """``(e, c)`` after ``c <- c / lambda_k``: a ``c`` over 1 halved (``e - 1``) or
        folded into the words (``e = 0``)."""
        p = self.p
        # c <- c / lambda_k ; c > 1: halve it (e - 1) or fold it into the words (e = 0)
        il = p[I_ONE_L] if windup else p[I_INV_LAM]
        c = self.sat(self.rsh(self.mul(c, il), p[I_C_S]), 0, p[I_L_HI], S_P)
        if c > p[I_ONE_L]:
            if e > 0:
                c = self.rsh(c, 1)
                e -= 1
            else:
                # V <- rsh(V c, c_s): c folded into the 64-bit values
                for i, j in self.stored():
                    self.Vput(i, j, self.rsh(self.Vget(i, j) * c, p[I_C_S]))
                c = p[I_ONE_L]
        return e, c

    def renormalise(self, e: int) -> int:
        """The block exponent after the largest left shift keeping tr P~ <= TR_HI."""
        p, n = self.p, self.n
        # block exponent: the largest left shift keeping tr P~ <= TR_HI (the words' trace);
        # V <- V 2^up, exactly
        tr = sum(self.P[i][i] for i in range(n))
        up_ = 0
        while 0 < tr * (1 << up_) and 2 * tr * (1 << up_) <= p[I_TR_HI] and e + up_ < p[I_E_MAX]:
            up_ += 1
        if up_:
            for i, j in self.stored():
                self.Vput(i, j, self.Vget(i, j) * (1 << up_))
            e += up_
        return e

    def trace(self, c: int) -> int:
        """:math:`\\mathrm{tr}P\\,2^{f_P - ps_{tr} + e}` as ``fixed_block`` reports it."""
        p = self.p
        trw = sum(self.rsh(self.P[i][i], p[I_TR_PS]) for i in range(self.n))
        return self.rsh(self.mul(trw, c), p[I_TC_S])


def reference_block(

    Phi: list[list[int]],
    Y: list[int],
    theta: list[int],
    P: list[list[int]],
    scale: list[int],
    counts: list[int],
    prm: list[int],
    acc_bits: int,
    mode: int = MODE_SYMMETRIC,
    theta_frac: list[int] | None = None,
    P_frac: list[list[int]] | None = None,
) -> tuple[list[int], list[int], list[int], list[int]]:
    r"""The same recursion in plain Python integers: the slow, readable specification.

    Written independently of :func:`fixed_block` (unbounded Python ints, floor
    division instead of shifts, no shared helpers) so that a test can prove the
    compiled kernel bit-exact. Every accumulator value is checked against
    ``acc_bits`` and every product against 63 bits: an ``AssertionError`` here would
    disprove the guard-bit argument.

    Parameters
    ----------
    Phi, Y : lists of int
        Rows of regressors and targets (Q integers, possibly out of range).
    theta, P, scale, counts : lists of int
        State (``P`` as a list of rows, ``scale = [e, c]``) and counters, updated
        in place.
    prm : list of int
        The plan (``I_*`` layout).
    acc_bits : int
        Accumulator width the plan was built for.
    mode : int
        ``MODE_SYMMETRIC``, ``MODE_LITERAL`` or ``MODE_NAIVE`` (frozen is not modelled).
    theta_frac : list of int, optional
        The fractions of ``theta`` in :math:`2^{-32}` LSB (``fixed_block``), updated in
        place; ``None``: zeros, not returned.
    P_frac : list of lists of int, optional
        The fractions of the words of ``P`` in :math:`2^{-32}` LSB, in
        :math:`[-2^{31}, 2^{31})` (``fixed_block``), updated in place; ``None``: zeros,
        not returned.

    Returns
    -------
    (eps, trace, exp, flags) : lists of int, one per row
    """
    tf = [0] * len(theta) if theta_frac is None else theta_frac
    Pf = [[0] * len(theta) for _ in range(len(theta))] if P_frac is None else P_frac
    ref = _Reference(P, Pf, counts, prm, acc_bits, mode)
    out_eps: list[int] = []
    out_tr: list[int] = []
    out_e: list[int] = []
    out_fl: list[int] = []
    for row, y_raw in zip(Phi, Y, strict=True):
        e, c = scale
        before = sum(counts)
        phg, y = ref.inputs(row, y_raw)
        eps = ref.error(phg, y, theta)
        h, w = ref.products(phg)
        sv = ref.denominator(phg, h, e, c)
        lam_k, flag = ref.forgetting(h, w, sv, e, c)
        gc, kg = ref.gain(lam_k, sv, e, c)
        flag |= ref.update(theta, tf, h, w, eps, gc, kg, e)
        e, c = ref.forget(e, c, bool(flag & FLAG_WINDUP))
        e = ref.renormalise(e)
        scale[0], scale[1] = e, c
        if sum(counts) > before:
            flag |= FLAG_SATURATION
        assert counts[S_ACC] == 0
        out_eps.append(eps)
        out_tr.append(ref.trace(c))
        out_e.append(e)
        out_fl.append(flag)
    return out_eps, out_tr, out_e, out_fl
