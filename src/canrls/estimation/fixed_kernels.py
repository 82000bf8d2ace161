r"""Compiled kernel of the fixed-point recursive least squares (private).

:class:`canrls.estimation.fixed.FixedRLS` owns the state, validates every argument and derives
the integer constants of the kernel (the *plan*, an ``int64`` vector indexed by the
``I_*`` constants below) from its :class:`~canrls.estimation.fixed.FixedConfig`. This module
only runs the recursion, in place, on preallocated ``int64`` arrays. It is the
bit-exact specification of the embedded kernel: every operation below is one a
32-bit microcontroller or DSP performs with the same result.

Integer operations (all on ``int64``, no floating point anywhere)
----------------------------------------------------------------
* **product**: ``a * b`` of two words (at most 32 bits each), exact: the
  multiplier's double-width output.
* **rounding right shift** ``rsh(x, s)``: round half up,
  ``(x + (1 << (s-1))) >> s`` with an arithmetic (floor) shift, as a DSP does with
  its rounding constant.
* **store to a word**: after the rounding shift the value is clamped to the word
  ``[lo, hi]``; every clamp increments the counter of its site. A negative output
  shift (a store to a *finer* format) is a left shift that saturates before
  shifting, so it cannot wrap either.
* **single product to a word** (``K``, ``P``, ...): the exact product is
  rounded once to the destination's scale and added to the destination with
  saturation, e.g. ``P_ij <- sat(P_ij - rsh(K_i h_j, s))``. ``theta`` is the exception:
  the estimate is 64 bits, the word ``theta`` and a fraction ``theta_frac`` in units of
  ``2^-32`` LSB, and ``K_i eps`` is added to it floored at ``2^-32`` LSB (from the high
  word of the product when the shift is 32 or more), then saturated to the word
  (:func:`_theta_add`): updates smaller than the LSB accumulate instead of rounding to 0.
* **multiply-accumulate** (``eps``, ``h``, ``phi' h``): sums of up to ``n`` products
  live in an accumulator of ``acc_bits``. It never overflows, by construction: the
  regressor operand is pre-shifted right (rounded) by the plan's guard shift
  ``ps`` so that ``n`` products at the largest magnitudes their words can hold, plus
  the additive term and the final rounding constant, stay below
  ``2**(acc_bits-1)`` for *every* input (the guard-bit argument of
  :mod:`canrls.estimation.fixed`). The ``acc`` saturation counter therefore stays 0; the
  pure-Python reference :func:`reference_block` asserts every accumulator value.
* **division**: exactly one per update, ``g = DIVIDEND // d`` with a dividend of
  ``acc_bits`` (``1 << (frac_g + frac_d)``) and a positive word divisor: C's
  truncating division (operands are positive, so floor and truncation agree; a
  non-positive divisor, possible only when :math:`P` has lost positive definiteness,
  gives ``g = hi`` and counts ``div``).

Scaled P (block exponent and forgetting scale)
----------------------------------------------
:math:`P` shrinks by orders of magnitude from :math:`P_0 = I/\alpha` as data arrive,
and grows by :math:`1/\lambda` per step in directions without data. It is stored as

.. math::

    P = c\,\tilde P\,2^{-(f_P + e)}, \qquad \tfrac12 < c \le 1, \quad e \ge 0

with integer words :math:`\tilde P`, a block exponent ``e`` and a forgetting scale
``c`` (a ``lam``-format word). :math:`h = P\varphi` and :math:`K` carry the same
exponent ``e``.

* Forgetting multiplies ``c`` by :math:`1/\lambda` (one product per step) instead
  of every word of :math:`P`; when ``c`` exceeds 1 it is halved and ``e`` lowered
  (the words do not move), or, at ``e = 0``, folded into the words
  (:math:`\tilde P \leftarrow c\tilde P`, ``c = 1``).
* After each update, when :math:`\mathrm{tr}\tilde P` has fallen to a quarter of the
  positive word range or below, the words are shifted left (exactly) and ``e``
  raised, so the trace sits in ``(range/4, range/2]``.

Every use of ``e`` is a shift, so this is still integer arithmetic; it keeps about
``word_bits - 3`` significant bits on :math:`\mathrm{tr}P` however small :math:`P`
becomes, and costs one product per step for forgetting.

Saturation sites
----------------
``SITES`` lists the counters in the order of the ``counts`` array: inputs
(``phi_in``, ``y_in``), then every store: ``eps``, ``h`` (:math:`\tilde P\varphi` and,
in the literal form, :math:`\tilde P^\top\varphi`), ``den`` (:math:`\varphi^\top\tilde
P\varphi` and :math:`d`), ``div`` (the quotient and :math:`g c`), ``K``, ``theta``,
``P`` (including ``c``), and ``acc`` (always 0, see above).

Per sample
----------
.. math::

    \varepsilon &= y - \varphi^\top\theta \\
    \tilde h &= \tilde P\varphi, \quad d = \lambda_k + c\,\varphi^\top\tilde h,
        \quad g = 1/d \\
    K &= (g c)\,\tilde h \qquad (= P\varphi/(\lambda_k + \varphi^\top P\varphi);
        \text{the high word of } (\tilde h\,2^k)(g c\,2^{g_{up}})) \\
    \theta &\leftarrow \theta + K\varepsilon \qquad\text{(the 64-bit estimate
        } \theta\,2^{32} + \theta_{frac}\text{, } K\varepsilon \text{ floored to } 2^{-32}
        \text{ LSB)} \\
    \tilde P &\leftarrow \tilde P - K\tilde h^\top \quad\text{(upper triangle only)},
        \qquad c \leftarrow c/\lambda_k

which is :math:`P \leftarrow (P - g\,hh^\top)/\lambda_k` with :math:`h = c\tilde h`.
:math:`\lambda_k = 1` instead of :math:`\lambda` when the trace the step would give,
:math:`(\mathrm{tr}P - g\,h^\top h)/\lambda`, exceeds ``trace_max`` (flag ``WINDUP``),
the rule of :mod:`canrls.estimation.rls`. To keep a single division it is decided before
dividing, from the equivalent division-free test
:math:`(\mathrm{tr}P - \lambda\,\mathrm{trace\_max})\,(\lambda + \varphi^\top P\varphi) > h^\top h`.
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
    "MODE_NAIVE",
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

from canrls.estimation.fixed_layout import (  # noqa: F401 - the layout, re-exported
    SITES,
    NSITES,
    S_PHI,
    S_Y,
    S_EPS,
    S_H,
    S_DEN,
    S_DIV,
    S_K,
    S_TH,
    S_P,
    S_ACC,
    MODE_SYMMETRIC,
    MODE_LITERAL,
    MODE_NAIVE,
    FLAG_WINDUP,
    FLAG_LOW_EXCITATION,
    FLAG_SATURATION,
    FLAG_FROZEN,
    I_PHI_LO,
    I_PHI_HI,
    I_Y_LO,
    I_Y_HI,
    I_EPS_LO,
    I_EPS_HI,
    I_H_LO,
    I_H_HI,
    I_DEN_LO,
    I_DEN_HI,
    I_G_LO,
    I_G_HI,
    I_K_LO,
    I_K_HI,
    I_TH_LO,
    I_TH_HI,
    I_P_LO,
    I_P_HI,
    I_L_LO,
    I_L_HI,
    I_PHI_PS,
    I_EPS_TS,
    I_EPS_OS,
    I_H_OS,
    I_S_OS,
    I_SC_S,
    I_LAM_D,
    I_ONE_D,
    I_DIVIDEND,
    I_GC_S,
    I_G_UP,
    I_TH_S,
    I_P_S,
    I_INV_LAM,
    I_ONE_L,
    I_C_S,
    I_TR_PS,
    I_TMAX,
    I_TMAX_LIM,
    I_TC_S,
    I_HC_S,
    I_VW_PS,
    I_LHS_PS,
    I_CMP_DF,
    I_E_MAX,
    I_TR_HI,
    NPARAM,
)


# ------------------------------------------------------- Q-format arithmetic
@numba.njit(cache=True, nogil=True, inline="always")
def round_shift(x: int, s: int) -> int:  # pragma: no cover - compiled
    """``x / 2**s`` rounded half up for ``s > 0`` (``x`` itself for ``s <= 0``).

    ``(x + (1 << (s-1))) >> s`` with an arithmetic shift. The caller guarantees
    ``|x| + 2**(s-1) < 2**63`` and ``s <= 62`` (the plan's guard bits do).
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
    if x == 0:
        return x, np.int64(0)
    t = min(-s, 63)
    # x 2^t > hi  <=>  x > floor(hi / 2^t) ;  x 2^t < lo  <=>  x < ceil(lo / 2^t)
    if x > (hi >> t):
        return hi, np.int64(1)
    if x < -((-lo) >> t):
        return lo, np.int64(1)
    return x << t, np.int64(0)


@numba.njit(cache=True, nogil=True, inline="always")
def sat_mul(a: int, b: int, s: int, lo: int, hi: int) -> tuple[int, int]:  # pragma: no cover
    """Saturating Q multiply: the product ``a*b`` stored with output shift ``s``.

    ``a`` and ``b`` are words of at most 32 bits, so the product is exact.
    """
    return store(a * b, s, lo, hi)


@numba.njit(cache=True, nogil=True, inline="always")
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


@numba.njit(cache=True, nogil=True, inline="always")
def _half(s: int) -> int:  # pragma: no cover - compiled
    """Rounding constant ``1 << (s-1)`` of a right shift by ``s`` (0 for ``s <= 0``)."""
    if s > 0:
        return np.int64(1) << (s - 1)
    return np.int64(0)


@numba.njit(cache=True, nogil=True, inline="always")
def _norm_shift(m: int) -> int:  # pragma: no cover - compiled
    """The left shift that brings ``0 <= m < 2**31`` to 30 bits: ``30 - bit_length(m)``.

    ``x << k`` then lies in ``[-2**30, 2**30)`` for every ``x`` with ``x ^ (x >> 63) <= m``
    (on the target: ``clz(m) - 2``; 30 for ``m = 0``).
    """
    k = 30
    while m > 0:
        m >>= 1
        k -= 1
    return max(k, 0)


@numba.njit(cache=True, nogil=True, inline="always")
def _rsh(x: int, s: int) -> int:  # pragma: no cover - compiled
    """Rounding right shift for ``0 <= s <= 62`` (``x`` itself for ``s = 0``)."""
    return (x + _half(s)) >> s


_FRAC_MASK = (1 << 32) - 1


@numba.njit(cache=True, nogil=True, inline="always")
def _theta_add(
    t: int, f: int, p: int, s: int, lo: int, hi: int
) -> tuple[int, int, int]:  # pragma: no cover - compiled
    """The 64-bit estimate ``t 2^32 + f`` (``0 <= f < 2^32``) plus the update ``p 2^-s`` LSB
    (``0 <= s <= 62``) at ``2^-32`` LSB: ``floor(p 2^(32-s))`` for ``s < 32``; for ``s >= 32``
    the high word of the product, ``floor(p / 2^32) 2^(64-s)`` (exact at this scale; the
    low word of ``p`` is dropped, as the target takes the high word of ``SMULL``).
    Saturated to ``[lo 2^32, hi 2^32 + 2^32 - 1]``. Returns ``(t, f, clamped)``."""
    whole = p >> s  # floor(p / 2^s): whole LSBs
    if s >= 32:
        part = ((p >> 32) << (64 - s)) & _FRAC_MASK  # the high word below the LSB
    else:
        part = (p & ((np.int64(1) << s) - 1)) << (32 - s)
    f = f + part
    t = t + whole + (f >> 32)
    f &= _FRAC_MASK
    if t > hi:
        return hi, _FRAC_MASK, 1
    if t < lo:
        return lo, 0, 1
    return t, f, 0


# -------------------------------------------------------------------- kernel
@numba.njit(cache=True, nogil=True)
def fixed_block(
    Phi: np.ndarray,
    Y: np.ndarray,
    theta: np.ndarray,
    theta_frac: np.ndarray,
    P: np.ndarray,
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
    theta_frac : ndarray of int64, shape (n,)
        The fraction of each estimate below its LSB, in units of :math:`2^{-32}` LSB
        (``0 <= theta_frac < 2**32``), updated in place: the estimate is the 64-bit
        ``theta * 2**32 + theta_frac``, of which ``theta`` is the published word
        (module docstring, *The estimate in 64 bits*).
    P : ndarray of int64, shape (n, n)
        The words :math:`\tilde P`, updated in place. ``MODE_SYMMETRIC`` reads and
        writes the upper triangle only (the lower one is never touched).
    scale : ndarray of int64, shape (2,)
        ``[e, c]``: block exponent and forgetting scale (module docstring),
        updated in place.
    work : ndarray of int64, shape (6, n)
        Scratch rows: ``phi`` (saturated input), ``phi >> ps`` (the guard shift),
        ``h~``, ``w~``, ``K`` and an accumulator row. On return ``work[4]`` holds the
        gain of the last row (zeros when it was not applied).
    counts : ndarray of int64, shape (NSITES,)
        Saturation counters, incremented in place.
    prm : ndarray of int64, shape (NPARAM,)
        The plan (``I_*`` layout), built by :class:`canrls.estimation.fixed.FixedRLS`.
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
    n = theta.shape[0]
    phi = work[0]
    phg = work[1]
    h = work[2]
    w = work[3]
    K = work[4]
    acc = work[5]
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
    g_lo = prm[I_G_LO]
    g_hi = prm[I_G_HI]
    th_lo = prm[I_TH_LO]
    th_hi = prm[I_TH_HI]
    P_lo = prm[I_P_LO]
    P_hi = prm[I_P_HI]
    l_hi = prm[I_L_HI]
    phi_ps = prm[I_PHI_PS]
    eps_ts = prm[I_EPS_TS]
    eps_os = prm[I_EPS_OS]
    h_os = prm[I_H_OS]
    s_os = prm[I_S_OS]
    sc_s = prm[I_SC_S]
    lam_d = prm[I_LAM_D]
    one_d = prm[I_ONE_D]
    dividend = prm[I_DIVIDEND]
    gc_s = prm[I_GC_S]
    g_up = prm[I_G_UP]
    th_s0 = prm[I_TH_S]
    P_s0 = prm[I_P_S]
    inv_lam = prm[I_INV_LAM]
    one_l = prm[I_ONE_L]
    c_s = prm[I_C_S]
    tr_ps = prm[I_TR_PS]
    tmax = prm[I_TMAX]
    tmax_lim = prm[I_TMAX_LIM]
    tc_s = prm[I_TC_S]
    hc_s = prm[I_HC_S]
    vw_ps = prm[I_VW_PS]
    lhs_ps = prm[I_LHS_PS]
    cmp_df = prm[I_CMP_DF]
    e_max = prm[I_E_MAX]
    tr_hi = prm[I_TR_HI]
    symmetric = mode == MODE_SYMMETRIC
    e = scale[0]
    c = scale[1]
    applied = 0
    # the diagonal of P~ summed >> tr_ps (carried from row to row)
    trw = np.int64(0)
    for i in range(n):
        trw += _rsh(P[i, i], tr_ps)

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
            # phi >> ps: the guard bits of the multiply-accumulates
            phg[j] = _rsh(v, phi_ps)
        x = Y[k]
        yk = min(max(x, y_lo), y_hi)
        c_y += yk != x

        # eps = y - phi' theta
        a = (yk << eps_ts) if eps_ts >= 0 else _rsh(yk, -eps_ts)
        for j in range(n):
            a -= phg[j] * theta[j]
        eps, cc = store(a, eps_os, eps_lo, eps_hi)
        c_eps += cc

        if frozen:
            flag = FLAG_FROZEN
            for i in range(n):
                K[i] = 0
        else:
            # h~ = P~ phi   (symmetric: P~_ij read from the upper triangle only)
            if symmetric:
                for i in range(n):
                    acc[i] = 0
                for i in range(n):
                    pi_ = phg[i]
                    # h_i = sum_{j<i} P_ji phi_j (scattered by the rows above) + P_ii phi_i
                    a = acc[i] + P[i, i] * pi_
                    for j in range(i + 1, n):
                        Pij = P[i, j]
                        # P_ij phi_j -> h_i ;  P_ji phi_i = P_ij phi_i -> h_j
                        a += Pij * phg[j]
                        acc[j] += Pij * pi_
                    v, cc = store(a, h_os, h_lo, h_hi)
                    c_h += cc
                    h[i] = v
                    w[i] = v
            else:
                # h~ = P~ phi (rows): P~ may have lost its symmetry
                for i in range(n):
                    a = np.int64(0)
                    for j in range(n):
                        a += P[i, j] * phg[j]
                    v, cc = store(a, h_os, h_lo, h_hi)
                    c_h += cc
                    h[i] = v
                    w[i] = v
                if mode == MODE_LITERAL:
                    # w~ = P~' phi (columns), i.e. the row phi' P~ as written
                    for i in range(n):
                        acc[i] = 0
                    for j in range(n):
                        pj = phg[j]
                        for i in range(n):
                            acc[i] += P[j, i] * pj
                    for i in range(n):
                        v, cc = store(acc[i], h_os, h_lo, h_hi)
                        c_h += cc
                        w[i] = v

            # s~ = phi' h~, brought from the scale of P (exponent e) to that of lambda
            a = np.int64(0)
            for i in range(n):
                a += phg[i] * h[i]
            st, cc = store(_rsh(a, e), s_os, den_lo, den_hi)
            c_den += cc
            # s = phi' P phi = c s~
            sv, cc = saturate(_rsh(st * c, sc_s), den_lo, den_hi)
            c_den += cc

            # windup <=> (tr P - g h'w)/lambda > trace_max
            #        <=> (tr P - lambda trace_max) (lambda + phi'P phi) > h'w
            lam_k = lam_d
            if tmax <= (tmax_lim >> e):
                # tr P = c tr P~   (trw: the diagonal summed >> tr_ps, kept from the last row)
                T = _rsh(trw * c, tc_s) - (tmax << e)
                if T > 0:
                    d_lam, cc = saturate(lam_d + sv, den_lo, den_hi)
                    a_vw = np.int64(0)
                    for i in range(n):
                        # h = c h~ ; w = c w~
                        hi_ = _rsh(h[i] * c, hc_s)
                        wi_ = _rsh(w[i] * c, hc_s)
                        a_vw += _rsh(hi_ * wi_, vw_ps)
                    lhs = _rsh(min(T, P_hi) * d_lam, lhs_ps)
                    # the two sides differ in scale by cmp_df - e bits
                    df = cmp_df - e
                    if df >= 0:
                        up = (lhs >> min(df, 63)) > a_vw
                    else:
                        up = lhs > (a_vw >> min(-df, 63))
                    if up:
                        lam_k = one_d
                        flag = FLAG_WINDUP

            # d = lambda_k + phi' P phi
            d, cc = saturate(lam_k + sv, den_lo, den_hi)
            c_den += cc
            # g = 1 / d     (the one division: acc-width dividend, word divisor, C truncation)
            if d <= 0:
                g = g_hi
                c_div += 1
            else:
                g = div_trunc(dividend, d)
                if g > g_hi:
                    g = g_hi
                    c_div += 1
            # gc = g c
            gc, cc = saturate(_rsh(g * c, gc_s), g_lo, g_hi)
            c_div += cc

            # normalisation of the updates (once per step): h~, w~ and eps shifted left
            # (exactly) to 31 bits, so that the theta and P updates take the high word
            # of their products (shifts >= 32 in the steady state; docs/fixed_point.md)
            m = np.int64(0)
            for i in range(n):
                m |= h[i] ^ (h[i] >> 63)
                m |= w[i] ^ (w[i] >> 63)
            kn = _norm_shift(m)
            kn = min(kn, (62 - P_s0 - e) >> 1, 62 - th_s0 - e)
            ke = min(_norm_shift(eps ^ (eps >> 63)), 62 - th_s0 - e - kn)
            epn = eps << ke
            gcn = gc << g_up
            th_s = th_s0 + e + kn + ke
            # K h~' has exponent 2e, P~ exponent e; K and h~ carry 2^kn each
            P_s = P_s0 + e + 2 * kn
            low = True
            for i in range(n):
                hs = h[i] << kn
                h[i] = hs
                w[i] = w[i] << kn
            for i in range(n):
                # K = P phi / (lambda + phi' P phi) = (g c) h~: the high word, rounded
                Ki = (h[i] * gcn + (np.int64(1) << 31)) >> 32
                K[i] = Ki
                # theta:theta_frac <- theta:theta_frac + K eps   (64 bits: K eps floored
                # to 2^-32 LSB, so that updates below the LSB accumulate; K carries the
                # exponent e + kn: shifted out here)
                v, f, cc = _theta_add(theta[i], theta_frac[i], Ki * epn, th_s, th_lo, th_hi)
                c_th += cc
                theta[i] = v
                theta_frac[i] = f
                # low excitation: the information K_i w~_i rounds to zero on the whole diagonal
                if _rsh(Ki * w[i], P_s) != 0:
                    low = False
            if symmetric:
                # P <- (P - g (P phi)(P phi)') / lambda:  P~ <- P~ - K h~'   upper triangle
                for i in range(n):
                    Ki = K[i]
                    for j in range(i, n):
                        v, cc = saturate(P[i, j] - _rsh(Ki * h[j], P_s), P_lo, P_hi)
                        c_P += cc
                        P[i, j] = v
            else:
                # P <- (P - K phi' P) / lambda:  P~ <- P~ - K w~', full matrix as written
                # (naive: w~ = h~, the row phi' P taken as (P phi)')
                for i in range(n):
                    Ki = K[i]
                    for j in range(n):
                        v, cc = saturate(P[i, j] - _rsh(Ki * w[j], P_s), P_lo, P_hi)
                        c_P += cc
                        P[i, j] = v
            if low:
                flag |= FLAG_LOW_EXCITATION

            # c <- c / lambda_k
            il = one_l if flag & FLAG_WINDUP else inv_lam
            c, cc = saturate(_rsh(c * il, c_s), np.int64(0), l_hi)
            c_P += cc
            if c > one_l:
                if e > 0:
                    # c/2 and 2^-e x 2: the words do not move
                    c = _rsh(c, 1)
                    e -= 1
                else:
                    # fold c into the words: P~ <- c P~, c = 1
                    for i in range(n):
                        for j in range(i if symmetric else 0, n):
                            v, cc = saturate(_rsh(P[i, j] * c, c_s), P_lo, P_hi)
                            c_P += cc
                            P[i, j] = v
                    c = one_l

            # block exponent: tr P~ fell to tr_hi/2 or below -> shift left by sh, e += sh
            tr = np.int64(0)
            trw = np.int64(0)
            for i in range(n):
                Pii = P[i, i]
                tr += Pii
                trw += _rsh(Pii, tr_ps)
            if tr > 0 and tr <= (tr_hi >> 1) and e < e_max:
                sh = 1
                while (tr << (sh + 1)) <= tr_hi and e + sh < e_max:
                    sh += 1
                for i in range(n):
                    for j in range(i if symmetric else 0, n):
                        v, cc = store(P[i, j], -sh, P_lo, P_hi)
                        c_P += cc
                        P[i, j] = v
                e += sh
                trw = np.int64(0)
                for i in range(n):
                    trw += _rsh(P[i, i], tr_ps)
            scale[0] = e
            scale[1] = c
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
        # tr P = c tr P~, recorded at the scale 2^-(f_P - tr_ps + e)
        eps_out[k] = eps
        trace_out[k] = _rsh(trw * c, tc_s)
        exp_out[k] = e
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
    scale: list[int],
    counts: list[int],
    prm: list[int],
    acc_bits: int,
    mode: int = MODE_SYMMETRIC,
    theta_frac: list[int] | None = None,
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

    Returns
    -------
    (eps, trace, exp, flags) : lists of int, one per row
    """
    n = len(theta)
    lim = 1 << (acc_bits - 1)
    p = prm
    tf = [0] * n if theta_frac is None else theta_frac

    def chk(a: int) -> int:
        # an accumulator value must fit in acc_bits (the guard-bit argument)
        assert -lim <= a < lim, f"accumulator {a} outside {acc_bits} bits"
        return a

    def mul(a: int, b: int) -> int:
        # product of two words: exact, and within the 64-bit product register
        assert abs(a) <= (1 << 32) and abs(b) <= (1 << 32), "operand wider than a word"
        x = a * b
        assert abs(x) < (1 << 63)
        return x

    def rsh(x: int, s: int) -> int:
        # x / 2^s rounded half up: floor(x / 2^s + 1/2)
        assert 0 <= s <= 62
        return (x + (1 << (s - 1))) // (1 << s) if s > 0 else x

    def sat(x: int, lo: int, hi: int, site: int | None) -> int:
        if x > hi or x < lo:
            if site is not None:
                counts[site] += 1
            return hi if x > hi else lo
        return x

    def put(a: int, s: int, lo: int, hi: int, site: int) -> int:
        # store an accumulator into a word: rounding half up (s > 0) or exact left shift
        chk(a)
        if s > 0:
            chk(a + (1 << (s - 1)))
            return sat(rsh(a, s), lo, hi, site)
        return sat(a * (1 << -s), lo, hi, site)

    def Pget(i: int, j: int) -> int:
        # symmetric form: only the upper triangle exists
        if mode == MODE_SYMMETRIC and i > j:
            return P[j][i]
        return P[i][j]

    out_eps: list[int] = []
    out_tr: list[int] = []
    out_e: list[int] = []
    out_fl: list[int] = []
    for row, y_raw in zip(Phi, Y, strict=True):
        e, c = scale
        before = sum(counts)
        flag = 0
        phi = [sat(int(x), p[I_PHI_LO], p[I_PHI_HI], S_PHI) for x in row]
        y = sat(int(y_raw), p[I_Y_LO], p[I_Y_HI], S_Y)
        phg = [rsh(x, p[I_PHI_PS]) for x in phi]
        # eps = y - phi' theta
        a = chk(y * (1 << p[I_EPS_TS]) if p[I_EPS_TS] >= 0 else rsh(y, -p[I_EPS_TS]))
        for j in range(n):
            a = chk(a - mul(phg[j], theta[j]))
        eps = put(a, p[I_EPS_OS], p[I_EPS_LO], p[I_EPS_HI], S_EPS)
        # h~ = P~ phi ; w~ = P~' phi
        h: list[int] = []
        w: list[int] = []
        for i in range(n):
            a = 0
            for j in range(n):
                a = chk(a + mul(Pget(i, j), phg[j]))
            h.append(put(a, p[I_H_OS], p[I_H_LO], p[I_H_HI], S_H))
        if mode != MODE_LITERAL:
            w = list(h)
        else:
            for i in range(n):
                a = 0
                for j in range(n):
                    a = chk(a + mul(Pget(j, i), phg[j]))
                w.append(put(a, p[I_H_OS], p[I_H_LO], p[I_H_HI], S_H))
        # s~ = phi' h~ at lambda's scale ; s = c s~
        a = 0
        for i in range(n):
            a = chk(a + mul(phg[i], h[i]))
        if e > 0:
            chk(a + (1 << (e - 1)))
        st = put(rsh(a, e), p[I_S_OS], p[I_DEN_LO], p[I_DEN_HI], S_DEN)
        sv = sat(rsh(mul(st, c), p[I_SC_S]), p[I_DEN_LO], p[I_DEN_HI], S_DEN)
        # windup <=> (c tr P~ - lambda trace_max) (lambda + s) > h' w
        lam_k = p[I_LAM_D]
        if p[I_TMAX] <= (p[I_TMAX_LIM] >> e):
            trw = 0
            for i in range(n):
                trw = chk(trw + rsh(P[i][i], p[I_TR_PS]))
            T = chk(rsh(mul(trw, c), p[I_TC_S]) - p[I_TMAX] * (1 << e))
            if T > 0:
                d_lam = sat(lam_k + sv, p[I_DEN_LO], p[I_DEN_HI], None)
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
        # d = lambda_k + s ; g = 1/d (C division, both operands positive)
        d = sat(lam_k + sv, p[I_DEN_LO], p[I_DEN_HI], S_DEN)
        if d <= 0:
            g = p[I_G_HI]
            counts[S_DIV] += 1
        else:
            g = sat(p[I_DIVIDEND] // d, p[I_G_LO], p[I_G_HI], S_DIV)
        gc = sat(rsh(mul(g, c), p[I_GC_S]), p[I_G_LO], p[I_G_HI], S_DIV)
        # normalisation: h~, w~ and eps shifted left to 31 bits (k, ke)
        def norm(m: int) -> int:
            assert 0 <= m < (1 << 31)
            return max(30 - m.bit_length(), 0)

        m = 0
        for x in h + w:
            m |= x if x >= 0 else -x - 1
        e0 = e
        k = min(norm(m), (62 - p[I_P_S] - e0) // 2, 62 - p[I_TH_S] - e0)
        ke = min(norm(eps if eps >= 0 else -eps - 1), 62 - p[I_TH_S] - e0 - k)
        hs = [x * (1 << k) for x in h]
        ws = [x * (1 << k) for x in w]
        gcn = gc * (1 << p[I_G_UP])
        assert all(-(1 << 31) <= x < (1 << 31) for x in hs + ws) and 0 <= gcn < (1 << 31)
        # K = (g c) h~: the high word of the product, rounded half up
        K = [rsh(mul(hs[i], gcn), 32) for i in range(n)]
        # theta 2^32 + tf <- theta 2^32 + tf + floor(K eps 2^32)   (the 64-bit estimate)
        for i in range(n):
            ts = p[I_TH_S] + e + k + ke
            u = mul(K[i], eps * (1 << ke))
            if ts >= 32:
                u = u // (1 << 32) * (1 << 32)  # the high word of the product (s >= 32)
            x = theta[i] * (1 << 32) + tf[i] + u * (1 << 32) // (1 << ts)
            top = p[I_TH_HI] * (1 << 32) + (1 << 32) - 1
            bot = p[I_TH_LO] * (1 << 32)
            if x > top or x < bot:
                counts[S_TH] += 1
                x = top if x > top else bot
            theta[i], tf[i] = x >> 32, x & ((1 << 32) - 1)
        # P~ <- P~ - K w~'   (upper triangle, or the full matrix for literal)
        ps = p[I_P_S] + e + 2 * k
        low = all(rsh(mul(K[i], ws[i]), ps) == 0 for i in range(n))
        for i in range(n):
            for j in range(i if mode == MODE_SYMMETRIC else 0, n):
                P[i][j] = sat(P[i][j] - rsh(mul(K[i], ws[j]), ps), p[I_P_LO], p[I_P_HI], S_P)
        if low:
            flag |= FLAG_LOW_EXCITATION
        # c <- c / lambda_k ; c > 1: halve it (e - 1) or fold it into the words (e = 0)
        il = p[I_ONE_L] if flag & FLAG_WINDUP else p[I_INV_LAM]
        c = sat(rsh(mul(c, il), p[I_C_S]), 0, p[I_L_HI], S_P)
        if c > p[I_ONE_L]:
            if e > 0:
                c = rsh(c, 1)
                e -= 1
            else:
                for i in range(n):
                    for j in range(i if mode == MODE_SYMMETRIC else 0, n):
                        P[i][j] = sat(rsh(mul(P[i][j], c), p[I_C_S]), p[I_P_LO], p[I_P_HI], S_P)
                c = p[I_ONE_L]
        # block exponent: the largest left shift keeping tr P~ <= TR_HI
        tr = sum(P[i][i] for i in range(n))
        up_ = 0
        while 0 < tr * (1 << up_) and 2 * tr * (1 << up_) <= p[I_TR_HI] and e + up_ < p[I_E_MAX]:
            up_ += 1
        if up_:
            for i in range(n):
                for j in range(i if mode == MODE_SYMMETRIC else 0, n):
                    P[i][j] = sat(P[i][j] * (1 << up_), p[I_P_LO], p[I_P_HI], S_P)
            e += up_
        scale[0], scale[1] = e, c
        if sum(counts) > before:
            flag |= FLAG_SATURATION
        assert counts[S_ACC] == 0
        out_eps.append(eps)
        trw = sum(rsh(P[i][i], p[I_TR_PS]) for i in range(n))
        out_tr.append(rsh(mul(trw, c), p[I_TC_S]))
        out_e.append(e)
        out_fl.append(flag)
    return out_eps, out_tr, out_e, out_fl
