"""Layout shared by the fixed-point specification and the C kernels (private).

The saturation sites, the update modes, the flag bits and the plan layout (the ``I_*``
indices of the ``int64`` plan vector built by :class:`canrls.estimation.fixed.estimator.FixedRLS`)
of :mod:`canrls.estimation.fixed.kernels` (the enums of ``src/canrls/c/host/fixed_spec.c``), in
a module of their own, so that :mod:`canrls.estimation.fixed.estimator` reads them without loading
the specification.
"""

from __future__ import annotations

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
#: ``mode``: the full-matrix update with ``phi' P`` taken as ``(P phi)'`` (equal only
#: while P is symmetric), as embedded code often writes it; for comparison only.
MODE_NAIVE = 2

# Flag bits: the values of canrls.estimation.rls.RLSFlag (checked by a test).
FLAG_WINDUP = 1
FLAG_LOW_EXCITATION = 2
FLAG_SATURATION = 4
FLAG_FROZEN = 8

# ---------------------------------------------------------------- plan layout
# Word ranges [lo, hi] of every stored quantity (c, the forgetting scale, is a lam word).
I_PHI_LO, I_PHI_HI, I_Y_LO, I_Y_HI = 0, 1, 2, 3
I_EPS_LO, I_EPS_HI, I_H_LO, I_H_HI = 4, 5, 6, 7
I_DEN_LO, I_DEN_HI, I_G_LO, I_G_HI = 8, 9, 10, 11
I_K_LO, I_K_HI, I_TH_LO, I_TH_HI = 12, 13, 14, 15
I_P_LO, I_P_HI, I_L_LO, I_L_HI = 16, 17, 18, 19
# the guard shift of phi shared by the three multiply-accumulates (phi' theta, P~ phi,
# phi' h~): phi >> PHI_PS enters every sum
I_PHI_PS = 20
# eps = y - phi' theta: alignment of y (>0: left), output shift
I_EPS_TS, I_EPS_OS = 21, 22
# h = P~ phi (and w = P~' phi): output shift
I_H_OS = 23
# s~ = phi' h at lambda's scale: output shift (after >> e)
I_S_OS = 24
# s = c s~ (shift of the product), lambda and 1 in the den format
I_SC_S, I_LAM_D, I_ONE_D = 25, 26, 27
# g = DIVIDEND // d ; gc = g c
I_DIVIDEND, I_GC_S = 28, 29
# K = high word of (h~ << k)(gc << G_UP); theta += K (eps << ke) (shift + e + k + ke),
# P~ -= K (h~ << k)' (shift + e + 2k)
I_G_UP, I_TH_S, I_P_S = 30, 31, 32
# c <- c / lambda_k: 1/lambda and 1 in the lam format, shift of the product
I_INV_LAM, I_ONE_L, I_C_S = 33, 34, 35
# trace bound: guard shift of the diagonal, lambda trace_max at the trace's scale,
# limit of lambda trace_max 2^e, shift of tr c
I_TR_PS, I_TMAX, I_TMAX_LIM, I_TC_S = 36, 37, 38, 39
# windup test: shift of h~ c, pre-shift of h_i w_i, of (tr P - lambda trace_max) d,
# scale difference of the two sides at e = 0
I_HC_S, I_VW_PS, I_LHS_PS, I_CMP_DF = 40, 41, 42, 43
# block exponent: largest e, and tr P~ is kept in (TR_HI/2, TR_HI] once e > 0
I_E_MAX, I_TR_HI = 44, 45
# normalised g: kg = max(0, bit_length(d) - KG_BL), at most KG_MAX (the dividend's room)
I_KG_BL, I_KG_MAX = 46, 47
NPARAM = 48
