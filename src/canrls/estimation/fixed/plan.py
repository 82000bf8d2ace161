r"""The plan of the fixed-point RLS: the kernel's integer constants and shifts.

:func:`build_plan` turns a :class:`~canrls.estimation.fixed.formats.FixedConfig`,
``n``, ``lam`` and ``trace_max`` into the ``int64`` plan vector of
:mod:`canrls.estimation.fixed.layout`, exactly (integers and fractions only).

Accumulators (guard bits)
-------------------------
The multiply-accumulates (:math:`\varphi^\top\theta`, :math:`\tilde P\varphi`,
:math:`\varphi^\top\tilde h`) sum ``n`` products in ``acc_bits``. They never overflow,
by construction rather than by a check: the plan shifts the regressor operand right
(rounded, once per sample, shared by the three sums) by the smallest guard shift for
which ``n`` products at the *largest representable* magnitudes of their words, plus
the additive term and the final rounding constant, stay below ``2**(acc_bits-1)``
(``constants["phi_ps"]``). Because every operand is a saturated word this holds for
every input, including a corrupted state; with 32-bit words and inputs and 64-bit
accumulators it costs 4-5 of the 30 fraction bits of :math:`\varphi`, far below the
LSB of the results. A configuration whose accumulator cannot hold the products at all
(32-bit words with a 32-bit accumulator) is rejected. The ``acc`` counter is kept so
every site is listed, and stays 0; the pure-Python reference
:func:`canrls.estimation.fixed.kernels.reference_block` asserts every accumulator value against
``acc_bits``.

Division
--------
One per update, modelled as the target does it: ``g = (1 << (frac_g + frac_den)) / d``,
an ``acc_bits`` dividend over a word divisor, truncated toward zero (C semantics).
Everything else multiplies: :math:`\lambda` and :math:`1/\lambda` are Q constants
computed once, exactly, from the rational value of ``lam`` (Python fractions, no
floating point) when the estimator is built (:attr:`FixedRLS.constants`).
"""

from __future__ import annotations

import functools
import math
from fractions import Fraction

import numpy as np
import numpy.typing as npt

from canrls.core.errors import FixedPointError
from canrls.estimation.fixed import layout as kernels
from canrls.estimation.fixed.formats import FixedConfig, QFormat

IntArray = npt.NDArray[np.int64]
FloatArray = npt.NDArray[np.float64]


# --------------------------------------------------------------------- plan
def _mac(
    acc_bits: int,
    phi: QFormat,
    b: QFormat,
    m: int,
    out: QFormat | None,
    term: QFormat | None = None,
    extra: int = 0,
) -> tuple[int, int, int]:
    """Shifts of one multiply-accumulate ``[term] + sum of m products (phi >> ps) * b -> out``.

    Returns ``(ps, ts, os)``: the guard shift of the ``phi`` operand (>= 0), the
    alignment of the term to the accumulator (> 0: left) and the output shift (> 0:
    rounding right shift). ``ps`` is the smallest for which the worst case (every
    operand at the largest magnitude its word holds) plus the rounding constant stays
    at or below ``2**(acc_bits - 1 - extra) - 1``.
    """
    lim = ((1 << (acc_bits - 1)) - 1) >> extra
    bmax = 1 << (b.bits - 1)
    for ps in range(0, 63):
        phimax = ((1 << (phi.bits - 1)) + ((1 << (ps - 1)) if ps else 0)) >> ps
        fa = phi.frac - ps + b.frac
        total = m * phimax * bmax
        ts = 0
        if term is not None:
            ts = fa - term.frac
            tmag = 1 << (term.bits - 1)
            total += tmag << ts if ts >= 0 else (tmag + (1 << (-ts - 1))) >> -ts
        os = 0 if out is None else fa - out.frac
        if os > 0:
            total += 1 << (os - 1)
        if total <= lim:
            return ps, ts, os
    raise FixedPointError(  # pragma: no cover - only absurd formats
        f"no guard shift of {phi} fits a {acc_bits}-bit accumulator"
    )


def _pre(acc_bits: int, a: QFormat, b: QFormat, m: int) -> int:
    """Pre-shift of each product of a rarely used multiply-accumulate (windup test)."""
    lim = (1 << (acc_bits - 1)) - 1
    pmax = (1 << (a.bits - 1)) * (1 << (b.bits - 1))
    for ps in range(0, 63):
        if m * ((pmax + ((1 << (ps - 1)) if ps else 0)) >> ps) <= lim:
            return ps
    raise FixedPointError("no pre-shift fits the accumulator")  # pragma: no cover


#: plans kept per process (:func:`build_plan`): every estimator of a configuration, and
#: each stream's (log's) estimators before their calibration, share one
PLANS_KEPT = 256


def build_plan(
    cfg: FixedConfig, n: int, lam: float, trace_max: float
) -> tuple[IntArray, dict[str, int]]:
    """The kernel's integer constants (``fixed.layout.I_*`` layout, read-only) and a
    named copy.

    Every constant is an exact function of the config, ``n``, the rational value of
    ``lam`` and ``trace_max``: Python integers and fractions, no floating point. So a
    plan is made once for its arguments (the last :data:`PLANS_KEPT`) and shared.
    """
    p, named = _plan(cfg, n, lam, trace_max)
    return p, dict(named)


@functools.lru_cache(maxsize=PLANS_KEPT)
def _plan(cfg: FixedConfig, n: int, lam: float, trace_max: float
          ) -> tuple[IntArray, dict[str, int]]:
    """:func:`build_plan`, made."""
    A = cfg.acc_bits
    p = np.zeros(kernels.NPARAM, dtype=np.int64)
    named: dict[str, int] = {}

    def put(i: int, name: str, v: int) -> None:
        if not -(1 << 63) <= v < (1 << 63):  # pragma: no cover - guarded by the checks
            raise FixedPointError(f"plan constant {name} = {v} does not fit 64 bits")
        p[i] = v
        named[name] = int(v)

    for q, lo_i, name in (
        (cfg.phi, kernels.I_PHI_LO, "phi"), (cfg.y, kernels.I_Y_LO, "y"),
        (cfg.eps, kernels.I_EPS_LO, "eps"), (cfg.h, kernels.I_H_LO, "h"),
        (cfg.den, kernels.I_DEN_LO, "den"), (cfg.g, kernels.I_G_LO, "g"),
        (cfg.K, kernels.I_K_LO, "K"), (cfg.theta, kernels.I_TH_LO, "theta"),
        (cfg.P, kernels.I_P_LO, "P"),
        (cfg.lam, kernels.I_L_LO, "lam"),
    ):  # fmt: skip
        put(lo_i, f"{name}_lo", q.lo)
        put(lo_i + 1, f"{name}_hi", q.hi)

    # the guard shift of phi: the largest the three multiply-accumulates need,
    #   eps = y - (phi >> ps)' theta ;  h~ = P~ (phi >> ps) ;  s~ = (phi >> ps)' h~ >> e
    # (s~ keeps one extra guard bit: the sum is then rounded by e bits)
    ps = max(
        _mac(A, cfg.phi, cfg.theta, n, cfg.eps, cfg.y)[0],
        _mac(A, cfg.phi, cfg.P, n, cfg.h)[0],
        _mac(A, cfg.phi, cfg.h, n, cfg.den, extra=1)[0],
    )
    if ps >= cfg.phi.bits - 1:
        raise FixedPointError(
            f"a {A}-bit accumulator cannot sum {n} products of phi {cfg.phi} "
            f"({cfg.phi.bits} bit) with {cfg.P.bits}-bit words: the guard shift {ps} "
            f"leaves no bit of phi"
        )
    put(kernels.I_PHI_PS, "phi_ps", ps)
    fa = cfg.phi.frac - ps + cfg.theta.frac
    put(kernels.I_EPS_TS, "eps_ts", fa - cfg.y.frac)
    put(kernels.I_EPS_OS, "eps_os", fa - cfg.eps.frac)
    put(kernels.I_H_OS, "h_os", cfg.phi.frac - ps + cfg.P.frac - cfg.h.frac)
    put(kernels.I_S_OS, "s_os", cfg.phi.frac - ps + cfg.h.frac - cfg.den.frac)
    # s = c s~ ; lambda and 1 in the den format
    put(kernels.I_SC_S, "sc_s", cfg.lam.frac)
    lam_d = cfg.den.to_int(Fraction(lam))
    one_d = cfg.den.to_int(1)
    if not 0 < lam_d <= one_d <= cfg.den.hi:
        raise FixedPointError(f"lam = {lam!r} and 1 must fit the den format {cfg.den}")
    put(kernels.I_LAM_D, "lam_den", lam_d)
    put(kernels.I_ONE_D, "one_den", one_d)
    # g = DIVIDEND // d ; gc = g c
    fdiv = cfg.g.frac + cfg.den.frac
    if fdiv > A - 2:
        raise FixedPointError(
            f"dividend 1 << (frac_g + frac_den) = 1 << {fdiv} of g {cfg.g} / den {cfg.den} "
            f"does not fit the {A}-bit accumulator"
        )
    put(kernels.I_DIVIDEND, "dividend", 1 << fdiv)
    put(kernels.I_GC_S, "gc_s", cfg.lam.frac)
    # single products rounded to their destination
    # K = rsh((h~ << k)(gc << g_up), 32): the high word of the product, with gc brought to
    # 32 bits; its fraction is then f_K' = f_h + k + f_g + g_up - 32 (exponent e)
    g_up = 32 - cfg.g.bits
    f_Kn = cfg.h.frac + cfg.g.frac + g_up - 32
    put(kernels.I_G_UP, "g_up", g_up)
    # g normalised: DIVIDEND 2^kg // d <= 2^(bits_g - 2) for d of bit length up to
    # kg_bl + kg, so that a large d (phi'P phi >= 1: the start, or data that suddenly
    # show a direction the prior held) still leaves g its bits; the dividend 2^(fdiv + kg)
    # must fit the accumulator
    put(kernels.I_KG_BL, "kg_bl", fdiv - cfg.g.bits + 3)
    put(kernels.I_KG_MAX, "kg_max", A - 2 - fdiv)
    put(kernels.I_TH_S, "theta_s", f_Kn + cfg.eps.frac - cfg.theta.frac)
    put(kernels.I_P_S, "P_s", f_Kn + cfg.h.frac - cfg.P.frac)
    # c <- c / lambda_k
    one_l = 1 << cfg.lam.frac
    inv_l = cfg.lam.to_int(1 / Fraction(lam))
    if not one_l <= inv_l <= cfg.lam.hi:
        raise FixedPointError(f"1/lam = {1 / lam!r} does not fit the lam format {cfg.lam}")
    put(kernels.I_INV_LAM, "inv_lam", inv_l)
    put(kernels.I_ONE_L, "one_lam", one_l)
    put(kernels.I_C_S, "c_s", cfg.lam.frac)
    # trace bound: the diagonal summed >> tr_ps must fit a word of min(P bits, A - 3) bits
    tw = min(cfg.P.bits, A - 3)
    tr_ps = 0
    while n * (((1 << (cfg.P.bits - 1)) + ((1 << (tr_ps - 1)) if tr_ps else 0)) >> tr_ps) >= (
        1 << (tw - 1)
    ):
        tr_ps += 1
    put(kernels.I_TR_PS, "trace_ps", tr_ps)
    put(kernels.I_TC_S, "tc_s", cfg.lam.frac)
    tr_cap = (1 << (tw - 1)) - 1  # tr P (times c <= 1) can never exceed this
    if math.isinf(trace_max):
        tmax = tr_cap
    else:
        lam_q = Fraction(cfg.lam.to_int(Fraction(lam)), one_l)
        tq = lam_q * Fraction(trace_max) * Fraction(2) ** (cfg.P.frac - tr_ps)
        tmax = min(math.floor(tq), tr_cap)
    put(kernels.I_TMAX, "trace_max_lam", tmax)
    put(kernels.I_TMAX_LIM, "trace_max_lim", 1 << (A - 3))
    # windup test: h = c h~, h'w pre-shifted, (tr P - lambda trace_max) d pre-shifted
    put(kernels.I_HC_S, "hc_s", cfg.lam.frac)
    vw_ps = _pre(A, cfg.h, cfg.h, n)
    lhs_ps = _pre(A, cfg.P, cfg.den, 1)
    put(kernels.I_VW_PS, "vw_ps", vw_ps)
    put(kernels.I_LHS_PS, "lhs_ps", lhs_ps)
    f_lhs = cfg.P.frac - tr_ps + cfg.den.frac - lhs_ps
    f_vw = 2 * cfg.h.frac - vw_ps
    put(kernels.I_CMP_DF, "cmp_scale_diff", f_lhs - f_vw)
    # block exponent of P: the window (tr_hi/2, tr_hi], and the largest exponent so
    # that every shift by (s + e) stays <= 62 and s~ >> e keeps its guard bit
    put(kernels.I_TR_HI, "trace_hi", 1 << (cfg.P.bits - 2))
    e_max = min(A - 3, 62 - named["theta_s"], 62 - named["P_s"])
    put(kernels.I_E_MAX, "e_max", e_max)
    for name, v in named.items():
        if name.endswith(("_ps", "_s")) and not 0 <= v <= 62:
            raise FixedPointError(
                f"shift {name} = {v} is outside 0..62: the Q formats of this configuration "
                f"are too far apart (or too close) for a {A}-bit accumulator"
            )
        if name.endswith(("_os", "_ts")) and abs(v) > 62:
            raise FixedPointError(f"shift {name} = {v} exceeds 62 bits")
    if e_max < 0:  # pragma: no cover - only absurd formats
        raise FixedPointError(f"no room for the block exponent of P {cfg.P}")
    p.setflags(write=False)  # shared by every estimator of these arguments
    return p, named


