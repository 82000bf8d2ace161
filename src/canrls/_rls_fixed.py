r"""Compiled kernel of the fixed-point recursive least squares (private).

:class:`canrls.fixed.FixedRLS` owns the state, validates every argument and derives
the integer constants of the kernel (the *plan*, an ``int64`` vector indexed by the
``I_*`` constants below) from its :class:`~canrls.fixed.FixedConfig`. This module
only runs the recursion, in place, on preallocated ``int64`` arrays. It is the
bit-exact specification of the embedded kernel: every operation below is one a
32-bit microcontroller or DSP performs with the same result.

Integer operations (all on ``int64``, no floating point anywhere)
----------------------------------------------------------------
* **product**: ``a * b`` of two words (at most 32 bits each), exact in 63 bits.
* **pre-shift** of a product before it enters an accumulator,
  ``(a*b + (1 << (ps-1))) >> ps`` (``ps = 0``: none). ``ps`` is chosen by the plan so
  that the sum of all products of a multiply-accumulate, plus its aligned additive
  term and the rounding constant of the final shift, provably stays inside
  ``acc_bits`` for *every* pair of operands that their words can hold. Accumulators
  therefore never overflow (the guard-bit argument of :mod:`canrls.fixed`), and the
  ``acc`` saturation counter stays 0 by construction; the pure-Python reference
  :func:`reference_block` asserts this on every accumulator value.
* **rounding right shift**: round half up, ``(x + (1 << (s-1))) >> s`` with an
  arithmetic (floor) shift, as a DSP does with its rounding constant.
* **store to a word**: after the rounding shift the value is clamped to the word
  ``[lo, hi]``; every clamp increments the counter of its site. A negative output
  shift (a store to a *finer* format) is a left shift that saturates before shifting,
  so it cannot wrap either.
* **division**: exactly one per update, ``g = DIVIDEND // d`` with a dividend of
  ``acc_bits`` (``1 << (frac_g + frac_d)``) and a positive word divisor: C's
  truncating division (operands are positive, so floor and truncation agree; a
  non-positive divisor, possible only when :math:`P` has lost positive definiteness,
  gives ``g = hi`` and counts ``div``).

Saturation sites
----------------
``SITES`` lists the counters in the order of the ``counts`` array: inputs
(``phi_in``, ``y_in``), then every store: ``eps``, ``h`` (:math:`P\varphi` and, in the
literal form, :math:`P^\top\varphi`), ``den`` (:math:`\lambda + \varphi^\top P\varphi`),
``div`` (the quotient), ``K``, ``theta``, ``P``, and ``acc`` (always 0, see above).

Per sample
----------
.. math::

    \varepsilon &= y - \varphi^\top\theta \\
    h &= P\varphi, \quad d = \lambda_k + \varphi^\top h, \quad g = 1/d \\
    K &= g\,h \\
    \theta &\leftarrow \theta + K\varepsilon \\
    P &\leftarrow (P - K h^\top)/\lambda_k \quad\text{(upper triangle only)}

:math:`\lambda_k = 1` instead of :math:`\lambda` when the trace the step would give,
:math:`(\mathrm{tr}P - g\,h^\top h)/\lambda`, exceeds ``trace_max`` (flag ``WINDUP``),
the rule of :mod:`canrls.rls`. To keep a single division it is decided before
dividing, from the equivalent division-free test
:math:`(\mathrm{tr}P - \lambda\,\mathrm{trace\_max})\,(\lambda + \varphi^\top h) > h^\top h`.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = [
    "SITES",
    "NSITES",
    "NPARAM",
    "MODE_SYMMETRIC",
    "MODE_LITERAL",
    "FLAG_WINDUP",
    "FLAG_LOW_EXCITATION",
    "FLAG_SATURATION",
    "FLAG_FROZEN",
    "round_shift",
    "saturate",
    "store",
    "sat_mul",
    "sat_add",
    "div_trunc",
    "fixed_block",
    "reference_block",
]

#: Saturation counters, in the order of the ``counts`` array.
SITES: tuple[str, ...] = (
    "phi_in", "y_in", "eps", "h", "den", "div", "K", "theta", "P", "acc",
)  # fmt: skip
NSITES = len(SITES)
S_PHI, S_Y, S_EPS, S_H, S_DEN, S_DIV, S_K, S_TH, S_P, S_ACC = range(NSITES)

#: ``mode``: symmetric update on the upper triangle (the embedded form).
MODE_SYMMETRIC = 0
#: ``mode``: the textbook full-matrix update ``P - K (phi' P)``, for comparison only.
MODE_LITERAL = 1

# Flag bits: the values of canrls.rls.RLSFlag (checked by a test).
FLAG_WINDUP = 1
FLAG_LOW_EXCITATION = 2
FLAG_SATURATION = 4
FLAG_FROZEN = 8

# ---------------------------------------------------------------- plan layout
# Word ranges [lo, hi] of every stored quantity.
I_PHI_LO, I_PHI_HI, I_Y_LO, I_Y_HI = 0, 1, 2, 3
I_EPS_LO, I_EPS_HI, I_H_LO, I_H_HI = 4, 5, 6, 7
I_DEN_LO, I_DEN_HI, I_G_LO, I_G_HI = 8, 9, 10, 11
I_K_LO, I_K_HI, I_TH_LO, I_TH_HI = 12, 13, 14, 15
I_P_LO, I_P_HI = 16, 17
# eps = y - phi' theta: product pre-shift, alignment of y (>0: left), output shift
I_EPS_PS, I_EPS_TS, I_EPS_OS = 18, 19, 20
# h = P phi (and w = P' phi)
I_H_PS, I_H_OS = 21, 22
# d = lambda_k + phi' h: lambda and 1 at the accumulator's scale
I_S_PS, I_S_OS, I_S_LAM, I_S_ONE = 23, 24, 25, 26
# g = DIVIDEND // d
I_DIVIDEND = 27
# K = g h
I_K_PS, I_K_OS = 28, 29
# theta + K eps
I_TH_PS, I_TH_TS, I_TH_OS = 30, 31, 32
# Kl = K * (1/lambda_k)
I_KL_PS, I_KL_OS = 33, 34
# P <- P * (1/lambda_k) - Kl h': pre-shifts of the two products, output shift
I_P_PS1, I_P_PS2, I_P_OS = 35, 36, 37
# 1/lambda and 1 in the lam format
I_INV_LAM, I_ONE_L = 38, 39
# trace bound: trace pre-shift, lambda*trace_max at the trace's scale, h'h pre-shift,
# pre-shift of the product (trP - lambda trace_max) d, right shifts of the two sides
I_TR_PS, I_TMAX, I_VW_PS, I_LHS_PS, I_CMP_SL, I_CMP_SR = 40, 41, 42, 43, 44, 45
NPARAM = 46


# ------------------------------------------------------- Q-format arithmetic
@numba.njit(cache=True, nogil=True, inline="always")
def round_shift(x: int, s: int) -> int:  # pragma: no cover - compiled
    """``x / 2**s`` rounded half up for ``s > 0`` (``x`` itself for ``s = 0``).

    ``(x + (1 << (s-1))) >> s`` with an arithmetic shift. The caller guarantees
    ``|x| + 2**(s-1) < 2**63`` (the plan's guard bits do).
    """
    if s <= 0:
        return x
    return (x + (np.int64(1) << (s - 1))) >> s


@numba.njit(cache=True, nogil=True, inline="always")
def saturate(x: int, lo: int, hi: int) -> tuple[int, int]:  # pragma: no cover - compiled
    """``x`` clamped to ``[lo, hi]``, and 1 if it was clamped (else 0)."""
    v = min(max(x, lo), hi)
    return v, np.int64(v != x)


@numba.njit(cache=True, nogil=True, inline="always")
def store(x: int, s: int, lo: int, hi: int) -> tuple[int, int]:  # pragma: no cover - compiled
    """Store an accumulator ``x`` (scale ``2**-(f+s)``) into a word of scale ``2**-f``.

    ``s >= 0``: rounding right shift then clamp. ``s < 0``: a left shift by ``-s``
    that clamps *before* shifting, so it never wraps. Returns ``(word, saturated)``.
    """
    if s >= 0:
        if s > 0:
            x = (x + (np.int64(1) << (s - 1))) >> s
        v = min(max(x, lo), hi)
        return v, np.int64(v != x)
    t = -s
    if x > (hi >> t):
        return hi, np.int64(1)
    if x < (lo >> t):
        return lo, np.int64(1)
    return x << t, np.int64(0)


@numba.njit(cache=True, nogil=True)
def sat_mul(a: int, b: int, s: int, lo: int, hi: int) -> tuple[int, int]:  # pragma: no cover
    """Saturating Q multiply: the product ``a*b`` stored with output shift ``s``.

    ``a`` and ``b`` are words of at most 32 bits, so the product is exact.
    """
    return store(a * b, s, lo, hi)


@numba.njit(cache=True, nogil=True)
def sat_add(a: int, b: int, lo: int, hi: int) -> tuple[int, int]:  # pragma: no cover
    """Saturating add ``a + b`` clamped to ``[lo, hi]`` (``|a|, |b| < 2**62``)."""
    return saturate(a + b, lo, hi)


@numba.njit(cache=True, nogil=True, inline="always")
def div_trunc(a: int, b: int) -> int:  # pragma: no cover - compiled
    """C division ``a / b`` of integers: the quotient truncated toward zero (``b != 0``)."""
    q = abs(a) // abs(b)
    if (a < 0) != (b < 0):
        return -q
    return q


# -------------------------------------------------------------------- kernel
@numba.njit(cache=True, nogil=True)
def fixed_block(
    Phi: np.ndarray,
    Y: np.ndarray,
    theta: np.ndarray,
    P: np.ndarray,
    work: np.ndarray,
    counts: np.ndarray,
    prm: np.ndarray,
    mode: int,
    frozen: bool,
    record: bool,
    eps_out: np.ndarray,
    theta_out: np.ndarray,
    trace_out: np.ndarray,
    flags_out: np.ndarray,
) -> int:  # pragma: no cover - compiled
    r"""Run the fixed-point recursion over the rows of ``Phi``, in place.

    Parameters
    ----------
    Phi : ndarray of int64, shape (N, n), C-contiguous
        Regressor rows in the ``phi`` Q format (saturated to it here, counted).
    Y : ndarray of int64, shape (N,)
        Targets in the ``y`` Q format (saturated to it here, counted).
    theta : ndarray of int64, shape (n,)
        Estimate in the ``theta`` format, updated in place.
    P : ndarray of int64, shape (n, n)
        :math:`P` in the ``P`` format, updated in place. ``MODE_SYMMETRIC`` reads and
        writes the upper triangle only (the lower one is never touched).
    work : ndarray of int64, shape (5, n)
        Scratch rows ``phi`` (saturated input), ``h = P phi``, ``w = P' phi``,
        ``K`` and an accumulator row. On return ``work[3]`` holds the gain of the
        last row (zeros when it was not applied).
    counts : ndarray of int64, shape (NSITES,)
        Saturation counters, incremented in place.
    prm : ndarray of int64, shape (NPARAM,)
        The plan (``I_*`` layout), built by :class:`canrls.fixed.FixedRLS`.
    mode : int
        ``MODE_SYMMETRIC`` or ``MODE_LITERAL``.
    frozen : bool
        Compute :math:`\varepsilon` only; ``theta`` and ``P`` stay untouched.
    record : bool
        Write ``theta`` after each row into ``theta_out`` (shape (N, n)).
    eps_out, trace_out : ndarray of int64, shape (N,)
        A-priori error (``eps`` format) and :math:`\mathrm{tr}P` (``P`` LSBs, exact
        sum) after each row.
    flags_out : ndarray of uint8, shape (N,)
        ``FLAG_*`` bits of each row.

    Returns
    -------
    int
        Number of rows that updated the state.
    """
    n = theta.shape[0]
    phi = work[0]
    h = work[1]
    w = work[2]
    K = work[3]
    acc_row = work[4]
    Kl = work[4]  # shares the accumulator row (h is stored before Kl is written)
    # ---- the plan, as locals
    phi_lo = prm[I_PHI_LO]
    phi_hi = prm[I_PHI_HI]
    y_lo = prm[I_Y_LO]
    y_hi = prm[I_Y_HI]
    eps_lo = prm[I_EPS_LO]
    eps_hi = prm[I_EPS_HI]
    h_lo = prm[I_H_LO]
    h_hi = prm[I_H_HI]
    den_lo = prm[I_DEN_LO]
    den_hi = prm[I_DEN_HI]
    g_hi = prm[I_G_HI]
    K_lo = prm[I_K_LO]
    K_hi = prm[I_K_HI]
    th_lo = prm[I_TH_LO]
    th_hi = prm[I_TH_HI]
    P_lo = prm[I_P_LO]
    P_hi = prm[I_P_HI]
    one = np.int64(1)
    eps_ps = prm[I_EPS_PS]
    eps_pr = (one << (eps_ps - 1)) if eps_ps > 0 else np.int64(0)
    eps_ts = prm[I_EPS_TS]
    eps_os = prm[I_EPS_OS]
    h_ps = prm[I_H_PS]
    h_pr = (one << (h_ps - 1)) if h_ps > 0 else np.int64(0)
    h_os = prm[I_H_OS]
    s_ps = prm[I_S_PS]
    s_pr = (one << (s_ps - 1)) if s_ps > 0 else np.int64(0)
    s_os = prm[I_S_OS]
    s_lam = prm[I_S_LAM]
    s_one = prm[I_S_ONE]
    dividend = prm[I_DIVIDEND]
    K_ps = prm[I_K_PS]
    K_pr = (one << (K_ps - 1)) if K_ps > 0 else np.int64(0)
    K_os = prm[I_K_OS]
    th_ps = prm[I_TH_PS]
    th_pr = (one << (th_ps - 1)) if th_ps > 0 else np.int64(0)
    th_ts = prm[I_TH_TS]
    th_os = prm[I_TH_OS]
    kl_ps = prm[I_KL_PS]
    kl_pr = (one << (kl_ps - 1)) if kl_ps > 0 else np.int64(0)
    kl_os = prm[I_KL_OS]
    p1_ps = prm[I_P_PS1]
    p1_pr = (one << (p1_ps - 1)) if p1_ps > 0 else np.int64(0)
    p2_ps = prm[I_P_PS2]
    p2_pr = (one << (p2_ps - 1)) if p2_ps > 0 else np.int64(0)
    p_os = prm[I_P_OS]
    inv_lam = prm[I_INV_LAM]
    one_l = prm[I_ONE_L]
    tr_ps = prm[I_TR_PS]
    tr_pr = (one << (tr_ps - 1)) if tr_ps > 0 else np.int64(0)
    tmax = prm[I_TMAX]
    vw_ps = prm[I_VW_PS]
    vw_pr = (one << (vw_ps - 1)) if vw_ps > 0 else np.int64(0)
    lhs_ps = prm[I_LHS_PS]
    lhs_pr = (one << (lhs_ps - 1)) if lhs_ps > 0 else np.int64(0)
    cmp_sl = prm[I_CMP_SL]
    cmp_sr = prm[I_CMP_SR]
    symmetric = mode == MODE_SYMMETRIC
    applied = 0

    for k in range(Phi.shape[0]):
        # per-step saturation counts, added to ``counts`` once per step
        c_phi = np.int64(0)
        c_y = np.int64(0)
        c_eps = np.int64(0)
        c_h = np.int64(0)
        c_den = np.int64(0)
        c_div = np.int64(0)
        c_K = np.int64(0)
        c_th = np.int64(0)
        c_P = np.int64(0)
        flag = 0

        # phi, y <- sat(phi), sat(y)       inputs clamped to their words
        for j in range(n):
            x = Phi[k, j]
            v = min(max(x, phi_lo), phi_hi)
            c_phi += v != x
            phi[j] = v
        x = Y[k]
        yk = min(max(x, y_lo), y_hi)
        c_y += yk != x

        # eps = y - phi' theta
        a = (yk << eps_ts) if eps_ts >= 0 else round_shift(yk, -eps_ts)
        for j in range(n):
            a -= (phi[j] * theta[j] + eps_pr) >> eps_ps
        eps, c = store(a, eps_os, eps_lo, eps_hi)
        c_eps += c

        if frozen:
            flag = FLAG_FROZEN
            for i in range(n):
                K[i] = 0
        else:
            # h = P phi   (symmetric: P_ij read from the upper triangle only)
            if symmetric:
                for i in range(n):
                    acc_row[i] = 0
                for i in range(n):
                    pi_ = phi[i]
                    # diagonal term P_ii phi_i
                    acc_row[i] += (P[i, i] * pi_ + h_pr) >> h_ps
                    for j in range(i + 1, n):
                        Pij = P[i, j]
                        # P_ij phi_j -> h_i ;  P_ji phi_i = P_ij phi_i -> h_j
                        acc_row[i] += (Pij * phi[j] + h_pr) >> h_ps
                        acc_row[j] += (Pij * pi_ + h_pr) >> h_ps
                for i in range(n):
                    v, c = store(acc_row[i], h_os, h_lo, h_hi)
                    c_h += c
                    h[i] = v
                    w[i] = v
            else:
                # h = P phi (rows), w = P' phi (columns): P may have lost its symmetry
                for i in range(n):
                    a = np.int64(0)
                    for j in range(n):
                        a += (P[i, j] * phi[j] + h_pr) >> h_ps
                    v, c = store(a, h_os, h_lo, h_hi)
                    c_h += c
                    h[i] = v
                for i in range(n):
                    acc_row[i] = 0
                for j in range(n):
                    pj = phi[j]
                    for i in range(n):
                        acc_row[i] += (P[j, i] * pj + h_pr) >> h_ps
                for i in range(n):
                    v, c = store(acc_row[i], h_os, h_lo, h_hi)
                    c_h += c
                    w[i] = v

            # s = phi' h   (accumulator; d = lambda_k + s below)
            a_s = np.int64(0)
            for i in range(n):
                a_s += (phi[i] * h[i] + s_pr) >> s_ps

            # tr P, at the scale of the trace bound
            trP = np.int64(0)
            for i in range(n):
                trP += (P[i, i] + tr_pr) >> tr_ps
            # windup <=> (tr P - g h'w)/lambda > trace_max
            #        <=> (tr P - lambda trace_max) (lambda + phi'P phi) > h'w
            lam_k = s_lam
            T = trP - tmax
            if T > 0:
                d_lam, c = store(a_s + s_lam, s_os, den_lo, den_hi)
                a_vw = np.int64(0)
                for i in range(n):
                    a_vw += (h[i] * w[i] + vw_pr) >> vw_ps
                Tw = min(T, P_hi)
                lhs = (Tw * d_lam + lhs_pr) >> lhs_ps
                if (lhs >> cmp_sl) > (a_vw >> cmp_sr):
                    lam_k = s_one
                    flag = FLAG_WINDUP

            # d = lambda_k + phi' P phi
            d, c = store(a_s + lam_k, s_os, den_lo, den_hi)
            c_den += c
            # g = 1 / d     (the one division: acc-width dividend, word divisor, C truncation)
            if d <= 0:
                g = g_hi
                c_div += 1
            else:
                g = div_trunc(dividend, d)
                if g > g_hi:
                    g = g_hi
                    c_div += 1

            # K = P phi / (lambda + phi' P phi) = g h
            for i in range(n):
                v, c = store((h[i] * g + K_pr) >> K_ps, K_os, K_lo, K_hi)
                c_K += c
                K[i] = v

            # theta <- theta + K eps
            for i in range(n):
                ti = theta[i]
                a = (ti << th_ts) if th_ts >= 0 else round_shift(ti, -th_ts)
                a += (K[i] * eps + th_pr) >> th_ps
                v, c = store(a, th_os, th_lo, th_hi)
                c_th += c
                theta[i] = v

            # 1/lambda_k
            il = one_l if flag == FLAG_WINDUP else inv_lam
            # Kl = K / lambda_k
            for i in range(n):
                v, c = store((K[i] * il + kl_pr) >> kl_ps, kl_os, K_lo, K_hi)
                c_K += c
                Kl[i] = v
            # low excitation: the information Kl_i h_i rounds to zero on the whole diagonal
            low = True
            for i in range(n):
                v, c = store((Kl[i] * w[i] + p2_pr) >> p2_ps, p_os, P_lo, P_hi)
                if v != 0:
                    low = False
            if symmetric:
                # P <- (P - g (P phi)(P phi)') / lambda = P/lambda - Kl h'   upper triangle
                for i in range(n):
                    Kli = Kl[i]
                    for j in range(i, n):
                        # P_ij / lambda - Kl_i h_j
                        a = ((P[i, j] * il + p1_pr) >> p1_ps) - ((Kli * h[j] + p2_pr) >> p2_ps)
                        v, c = store(a, p_os, P_lo, P_hi)
                        c_P += c
                        P[i, j] = v
            else:
                # P <- (P - K phi' P) / lambda = P/lambda - Kl w', full matrix as written
                for i in range(n):
                    Kli = Kl[i]
                    for j in range(n):
                        # P_ij / lambda - Kl_i (phi' P)_j
                        a = ((P[i, j] * il + p1_pr) >> p1_ps) - ((Kli * w[j] + p2_pr) >> p2_ps)
                        v, c = store(a, p_os, P_lo, P_hi)
                        c_P += c
                        P[i, j] = v
            if low:
                # the sample's information g h_i^2 rounds to zero on the whole diagonal
                flag |= FLAG_LOW_EXCITATION
            applied += 1

        nsat = c_phi + c_y + c_eps + c_h + c_den + c_div + c_K + c_th + c_P
        if nsat > 0:
            flag |= FLAG_SATURATION
            counts[S_PHI] += c_phi
            counts[S_Y] += c_y
            counts[S_EPS] += c_eps
            counts[S_H] += c_h
            counts[S_DEN] += c_den
            counts[S_DIV] += c_div
            counts[S_K] += c_K
            counts[S_TH] += c_th
            counts[S_P] += c_P
        trace = np.int64(0)
        for i in range(n):
            trace += P[i, i]
        eps_out[k] = eps
        trace_out[k] = trace
        flags_out[k] = flag
        if record:
            for i in range(n):
                theta_out[k, i] = theta[i]
    return applied


# ------------------------------------------------------ pure-Python reference
def reference_block(
    Phi: list[list[int]],
    Y: list[int],
    theta: list[int],
    P: list[list[int]],
    counts: list[int],
    prm: list[int],
    acc_bits: int,
    mode: int = MODE_SYMMETRIC,
) -> tuple[list[int], list[int], list[int]]:
    r"""The same recursion in plain Python integers: the slow, readable specification.

    Written independently of :func:`fixed_block` (unbounded Python ints, no shared
    helpers, no in-place tricks) so that a test can prove the compiled kernel
    bit-exact. Every accumulator value is checked against ``acc_bits``: an
    ``AssertionError`` here would disprove the guard-bit argument.

    Parameters
    ----------
    Phi, Y : lists of int
        Rows of regressors and targets (Q integers, possibly out of range).
    theta, P, counts : lists of int
        State and counters, updated in place (``P`` as a list of rows).
    prm : list of int
        The plan (``I_*`` layout).
    acc_bits : int
        Accumulator width the plan was built for.
    mode : int
        ``MODE_SYMMETRIC`` or ``MODE_LITERAL``.

    Returns
    -------
    (eps, trace, flags) : lists of int, one per row
    """
    n = len(theta)
    lim = 1 << (acc_bits - 1)

    def chk(a: int) -> int:
        # every accumulator value must fit in acc_bits (the guard-bit argument)
        assert -lim <= a < lim, f"accumulator {a} outside {acc_bits} bits"
        return a

    def mul(a: int, b: int, ps: int) -> int:
        # product of two words (exact), pre-shifted with rounding half up into the accumulator
        p = a * b
        assert abs(p) < (1 << 62) + 1, "product of two words exceeds 63 bits"
        if ps > 0:
            p = (p + (1 << (ps - 1))) // (1 << ps)
        return chk(p)

    def align(x: int, s: int) -> int:
        # additive term brought to the accumulator scale
        if s >= 0:
            return chk(x * (1 << s))
        return chk((x + (1 << (-s - 1))) // (1 << -s))

    def put(a: int, s: int, lo: int, hi: int, site: int | None) -> int:
        # store the accumulator a into a word: rounding half up, then saturation
        chk(a)
        if s > 0:
            v = chk(a + (1 << (s - 1))) // (1 << s)
        else:
            v = a * (1 << -s)
        if v > hi or v < lo:
            if site is not None:
                counts[site] += 1
            v = hi if v > hi else lo
        return v

    def clamp(x: int, lo: int, hi: int, site: int) -> int:
        if x > hi or x < lo:
            counts[site] += 1
            return hi if x > hi else lo
        return x

    def Pget(i: int, j: int) -> int:
        # symmetric form: only the upper triangle exists
        if mode == MODE_SYMMETRIC and i > j:
            return P[j][i]
        return P[i][j]

    eps_l: list[int] = []
    tr_l: list[int] = []
    fl_l: list[int] = []
    for row, y_raw in zip(Phi, Y, strict=True):
        before = sum(counts)
        flag = 0
        phi = [clamp(int(x), prm[I_PHI_LO], prm[I_PHI_HI], S_PHI) for x in row]
        y = clamp(int(y_raw), prm[I_Y_LO], prm[I_Y_HI], S_Y)
        # eps = y - phi' theta
        a = align(y, prm[I_EPS_TS])
        for j in range(n):
            a = chk(a - mul(phi[j], theta[j], prm[I_EPS_PS]))
        eps = put(a, prm[I_EPS_OS], prm[I_EPS_LO], prm[I_EPS_HI], S_EPS)
        # h = P phi ; w = P' phi
        h: list[int] = []
        w: list[int] = []
        for i in range(n):
            a = 0
            for j in range(n):
                a = chk(a + mul(Pget(i, j), phi[j], prm[I_H_PS]))
            h.append(put(a, prm[I_H_OS], prm[I_H_LO], prm[I_H_HI], S_H))
        if mode == MODE_SYMMETRIC:
            w = list(h)
        else:
            for i in range(n):
                a = 0
                for j in range(n):
                    a = chk(a + mul(Pget(j, i), phi[j], prm[I_H_PS]))
                w.append(put(a, prm[I_H_OS], prm[I_H_LO], prm[I_H_HI], S_H))
        # s = phi' h
        a_s = 0
        for i in range(n):
            a_s = chk(a_s + mul(phi[i], h[i], prm[I_S_PS]))
        # windup <=> (tr P - lambda trace_max) (lambda + s) > h' w
        trP = 0
        for i in range(n):
            trP = chk(trP + align(P[i][i], -prm[I_TR_PS]))
        lam_k = prm[I_S_LAM]
        T = trP - prm[I_TMAX]
        if T > 0:
            d_lam = put(chk(a_s + lam_k), prm[I_S_OS], prm[I_DEN_LO], prm[I_DEN_HI], None)
            a_vw = 0
            for i in range(n):
                a_vw = chk(a_vw + mul(h[i], w[i], prm[I_VW_PS]))
            lhs = mul(min(T, prm[I_P_HI]), d_lam, prm[I_LHS_PS])
            if lhs // (1 << prm[I_CMP_SL]) > a_vw // (1 << prm[I_CMP_SR]):
                lam_k = prm[I_S_ONE]
                flag = FLAG_WINDUP
        # d = lambda_k + phi' P phi
        d = put(chk(a_s + lam_k), prm[I_S_OS], prm[I_DEN_LO], prm[I_DEN_HI], S_DEN)
        # g = 1 / d: C division, truncation toward zero
        if d <= 0:
            g = prm[I_G_HI]
            counts[S_DIV] += 1
        else:
            g = prm[I_DIVIDEND] // d
            if g > prm[I_G_HI]:
                g = prm[I_G_HI]
                counts[S_DIV] += 1
        # K = g h
        K = [
            put(mul(h[i], g, prm[I_K_PS]), prm[I_K_OS], prm[I_K_LO], prm[I_K_HI], S_K)
            for i in range(n)
        ]
        # theta <- theta + K eps
        for i in range(n):
            a = chk(align(theta[i], prm[I_TH_TS]) + mul(K[i], eps, prm[I_TH_PS]))
            theta[i] = put(a, prm[I_TH_OS], prm[I_TH_LO], prm[I_TH_HI], S_TH)
        # Kl = K / lambda_k
        il = prm[I_ONE_L] if flag == FLAG_WINDUP else prm[I_INV_LAM]
        Kl = [
            put(mul(K[i], il, prm[I_KL_PS]), prm[I_KL_OS], prm[I_K_LO], prm[I_K_HI], S_K)
            for i in range(n)
        ]
        # low excitation: Kl_i w_i rounds to zero in P for every i
        low = all(
            put(mul(Kl[i], w[i], prm[I_P_PS2]), prm[I_P_OS], prm[I_P_LO], prm[I_P_HI], None) == 0
            for i in range(n)
        )
        # P <- P / lambda_k - Kl w'   (upper triangle, or the full matrix for literal)
        for i in range(n):
            for j in range(i if mode == MODE_SYMMETRIC else 0, n):
                a = chk(mul(P[i][j], il, prm[I_P_PS1]) - mul(Kl[i], w[j], prm[I_P_PS2]))
                P[i][j] = put(a, prm[I_P_OS], prm[I_P_LO], prm[I_P_HI], S_P)
        if low:
            flag |= FLAG_LOW_EXCITATION
        if sum(counts) > before:
            flag |= FLAG_SATURATION
        assert counts[S_ACC] == 0
        eps_l.append(eps)
        tr_l.append(sum(P[i][i] for i in range(n)))
        fl_l.append(flag)
    return eps_l, tr_l, fl_l
