/*
 * plan_fields.h -- the fields of canrls_plan_q31 (canrls_fixed.h) in declaration order,
 * as an X-macro: the order in which canrls._fixed and canrls._target read a plan
 * vector, exported to Python as PLAN_FIELDS so that the two sides cannot drift.
 *
 * SPDX-License-Identifier: MIT
 */
#ifndef CANRLS_PLAN_FIELDS_H
#define CANRLS_PLAN_FIELDS_H

#define CANRLS_PLAN_FIELDS(X)                                                           \
    X(phi_lo) X(phi_hi) X(y_lo) X(y_hi) X(eps_lo) X(eps_hi) X(h_lo) X(h_hi) X(den_lo)    \
    X(den_hi) X(g_lo) X(g_hi) X(K_lo) X(K_hi) X(theta_lo) X(theta_hi) X(P_lo) X(P_hi)    \
    X(lam_lo) X(lam_hi) X(phi_ps) X(eps_ts) X(eps_os) X(h_os) X(s_os) X(sc_s) X(lam_den) \
    X(one_den) X(dividend) X(gc_s) X(g_up) X(kg_bl) X(kg_max) X(theta_s) X(P_s)          \
    X(inv_lam) X(one_lam) X(c_s) X(trace_ps) X(tc_s) X(trace_max_lam) X(trace_max_lim)    \
    X(hc_s) X(vw_ps) X(lhs_ps) X(cmp_scale_diff) X(trace_hi) X(e_max)

#endif /* CANRLS_PLAN_FIELDS_H */
