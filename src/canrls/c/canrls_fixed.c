/*
 * canrls_fixed.c -- fixed-point recursive least squares, the embedded kernel.
 *
 * SPDX-License-Identifier: MIT
 *
 * Line for line the symmetric form of the Python specification
 * (canrls.estimation.fixed_kernels.fixed_block): the same names, the same order of
 * operations, the equation beside each line. See canrls_fixed.h for the numbers.
 */
#include "canrls_fixed.h"

#include <string.h>

/* The kernel needs an arithmetic (floor) right shift of negative values, which C99
 * leaves to the implementation; every compiler for a DSP or a microcontroller has it.
 * Refuse to build where it is missing. */
typedef char canrls_needs_arithmetic_shift[((-8 >> 1) == -4) ? 1 : -1];
typedef char canrls_needs_arithmetic_shift64[(((int64_t)-8 >> 1) == -4) ? 1 : -1];

/* ------------------------------------------------------- Q-format arithmetic */

/* rsh(x, s) = x / 2^s rounded half up, (x + 2^(s-1)) >> s, for 0 <= s <= 62
 * (Python _rsh; the caller guarantees |x| + 2^(s-1) < 2^63). */
static inline int64_t rsh(int64_t x, int32_t s)
{
    return s > 0 ? (x + ((int64_t)1 << (s - 1))) >> s : x;
}

/* rsh of a word: ((x >> (s-1)) + 1) >> 1 equals (x + 2^(s-1)) >> s and cannot overflow. */
static inline int32_t rsh32(int32_t x, int32_t s)
{
    return s > 0 ? ((x >> (s - 1)) + 1) >> 1 : x;
}

/* sat(x) = x clamped to [lo, hi]; a clamp increments *n (Python saturate). */
static inline int32_t sat(int64_t x, int32_t lo, int32_t hi, uint32_t *n)
{
    if (x > hi) {
        *n += 1u;
        return hi;
    }
    if (x < lo) {
        *n += 1u;
        return lo;
    }
    return (int32_t)x;
}

/* Store an accumulator x (scale 2^-(f+s)) into a word of scale 2^-f (Python store):
 * s >= 0: rounding right shift then clamp; s < 0: a left shift that clamps before
 * shifting, so it never wraps. */
static inline int32_t store(int64_t x, int32_t s, int32_t lo, int32_t hi, uint32_t *n)
{
    int32_t t;
    if (s >= 0) {
        return sat(rsh(x, s), lo, hi, n);
    }
    if (x == 0) {
        return 0;
    }
    t = -s < 63 ? -s : 63;
    /* x 2^t > hi  <=>  x > floor(hi / 2^t) ;  x 2^t < lo  <=>  x < ceil(lo / 2^t) */
    if (x > ((int64_t)hi >> t)) {
        *n += 1u;
        return hi;
    }
    if (x < -((-(int64_t)lo) >> t)) {
        *n += 1u;
        return lo;
    }
    return (int32_t)(x * ((int64_t)1 << t));
}

/* ------------------------------------------------------------------- set-up */

/* trw = sum_i rsh(Pw_ii, trace_ps): the trace at the windup test's scale */
static int32_t trace_words(const canrls_rls_q31 *S)
{
    const int32_t *Pii = S->P;
    int64_t trw = 0;
    uint32_t i;
    for (i = 0; i < S->n; i++) {
        trw += rsh(*Pii, S->plan->trace_ps);
        Pii += S->n - i; /* the next diagonal word of the packed rows */
    }
    return (int32_t)trw;
}

int canrls_init_q31(canrls_rls_q31 *S, const canrls_plan_q31 *plan, uint32_t n,
                    const int32_t *p0, int32_t e0)
{
    uint32_t i;
    if (S == NULL || plan == NULL || p0 == NULL || n < 1u || n > CANRLS_N_MAX
        || e0 < 0 || e0 > plan->e_max) {
        return CANRLS_EINVAL;
    }
    for (i = 0; i < n; i++) {
        if (p0[i] < plan->P_lo || p0[i] > plan->P_hi) {
            return CANRLS_EINVAL;
        }
    }
    memset(S, 0, sizeof *S);
    S->plan = plan;
    S->n = n;
    /* P0 = diag(p0) 2^-(f_P + e0), c = 1 ; theta0 = 0 */
    for (i = 0; i < n; i++) {
        S->P[canrls_tri_index(n, i, i)] = p0[i];
    }
    S->e = e0;
    S->c = plan->one_lam;
    S->trw = trace_words(S);
    return CANRLS_OK;
}

int canrls_restore_q31(canrls_rls_q31 *S, const int32_t *theta, const int32_t *P_up,
                       int32_t e, int32_t c)
{
    const canrls_plan_q31 *p;
    uint32_t i, m;
    if (S == NULL || S->plan == NULL || theta == NULL || P_up == NULL) {
        return CANRLS_EINVAL;
    }
    p = S->plan;
    m = CANRLS_TRI(S->n);
    if (e < 0 || e > p->e_max || c < 1 || c > p->one_lam) {
        return CANRLS_EINVAL;
    }
    for (i = 0; i < S->n; i++) {
        if (theta[i] < p->theta_lo || theta[i] > p->theta_hi) {
            return CANRLS_EINVAL;
        }
    }
    for (i = 0; i < m; i++) {
        if (P_up[i] < p->P_lo || P_up[i] > p->P_hi) {
            return CANRLS_EINVAL;
        }
    }
    memcpy(S->theta, theta, S->n * sizeof *theta);
    memcpy(S->P, P_up, m * sizeof *P_up);
    S->e = e;
    S->c = c;
    S->trw = trace_words(S);
    return CANRLS_OK;
}

/* ------------------------------------------------------------------- kernel */

int canrls_update_q31(canrls_rls_q31 *S, const int32_t *phi, int32_t y,
                      canrls_step_q31 *step)
{
    const canrls_plan_q31 *p = S->plan;
    const uint32_t n = S->n;
    int32_t *const theta = S->theta;
    int32_t *const P = S->P;
    int32_t *const h = S->h;
    int32_t *const K = S->K;
    int32_t *const phg = S->phg;
    int64_t *const acc = S->acc;
    int32_t e = S->e;
    int32_t c = S->c;
    int32_t trw = S->trw;
    /* per-step saturation counts, added to S->counts once per step */
    uint32_t c_phi = 0, c_y = 0, c_eps = 0, c_h = 0, c_den = 0, c_div = 0, c_K = 0,
             c_th = 0, c_P = 0;
    uint32_t flag = 0;
    uint32_t i, j;
    int32_t yk, eps;
    int64_t a;
    int applied = 0;

    /* phi, y <- sat(phi), sat(y)       inputs clamped to their words */
    for (j = 0; j < n; j++) {
        int32_t v = sat(phi[j], p->phi_lo, p->phi_hi, &c_phi);
        /* phi >> ps: the guard bits of the multiply-accumulates */
        phg[j] = rsh32(v, p->phi_ps);
    }
    yk = sat(y, p->y_lo, p->y_hi, &c_y);

    /* eps = y - phi' theta */
    a = p->eps_ts >= 0 ? (int64_t)yk * ((int64_t)1 << p->eps_ts) : rsh(yk, -p->eps_ts);
    for (j = 0; j < n; j++) {
        a -= (int64_t)phg[j] * theta[j];
    }
    eps = store(a, p->eps_os, p->eps_lo, p->eps_hi, &c_eps);

    if (S->frozen) {
        flag = CANRLS_FLAG_FROZEN;
        memset(K, 0, n * sizeof *K);
    } else {
        const int32_t *Pr; /* row i of the packed upper triangle (read) */
        int32_t *Pw;       /* row i of the packed upper triangle (written) */
        int32_t st, sv, lam_k, d, g, gc, th_s, P_s;
        int32_t il;
        int low;

        /* h~ = P~ phi   (symmetric: P~_ij read from the upper triangle only) */
        for (i = 0; i < n; i++) {
            acc[i] = 0;
        }
        Pr = P;
        for (i = 0; i < n; i++) {
            const int32_t pi_ = phg[i];
            /* h_i = sum_{j<i} P_ji phi_j (scattered by the rows above) + P_ii phi_i */
            a = acc[i] + (int64_t)Pr[0] * pi_;
            for (j = i + 1; j < n; j++) {
                const int32_t Pij = Pr[j - i];
                /* P_ij phi_j -> h_i ;  P_ji phi_i = P_ij phi_i -> h_j */
                a += (int64_t)Pij * phg[j];
                acc[j] += (int64_t)Pij * pi_;
            }
            h[i] = store(a, p->h_os, p->h_lo, p->h_hi, &c_h);
            Pr += n - i;
        }

        /* s~ = phi' h~, brought from the scale of P (exponent e) to that of lambda */
        a = 0;
        for (i = 0; i < n; i++) {
            a += (int64_t)phg[i] * h[i];
        }
        st = store(rsh(a, e), p->s_os, p->den_lo, p->den_hi, &c_den);
        /* s = phi' P phi = c s~ */
        sv = sat(rsh((int64_t)st * c, p->sc_s), p->den_lo, p->den_hi, &c_den);

        /* windup <=> (tr P - g h'h)/lambda > trace_max
         *        <=> (tr P - lambda trace_max) (lambda + phi'P phi) > h'h */
        lam_k = p->lam_den;
        if (p->trace_max_lam <= (p->trace_max_lim >> e)) {
            /* tr P = c tr P~   (trw: the diagonal summed >> tr_ps, kept from the last row) */
            int64_t T = rsh((int64_t)trw * c, p->tc_s)
                        - (int64_t)p->trace_max_lam * ((int64_t)1 << e);
            if (T > 0) {
                uint32_t none = 0; /* d_lam is not counted */
                int32_t d_lam = sat((int64_t)p->lam_den + sv, p->den_lo, p->den_hi, &none);
                int64_t a_vw = 0, lhs;
                int32_t df;
                int up;
                for (i = 0; i < n; i++) {
                    /* h = c h~ ; w = c w~ = h */
                    int64_t hi_ = rsh((int64_t)h[i] * c, p->hc_s);
                    int64_t wi_ = rsh((int64_t)h[i] * c, p->hc_s);
                    a_vw += rsh(hi_ * wi_, p->vw_ps);
                }
                lhs = rsh((T < p->P_hi ? T : p->P_hi) * d_lam, p->lhs_ps);
                /* the two sides differ in scale by cmp_df - e bits */
                df = p->cmp_scale_diff - e;
                if (df >= 0) {
                    up = (lhs >> (df < 63 ? df : 63)) > a_vw;
                } else {
                    up = lhs > (a_vw >> (-df < 63 ? -df : 63));
                }
                if (up) {
                    lam_k = p->one_den;
                    flag = CANRLS_FLAG_WINDUP;
                }
            }
        }

        /* d = lambda_k + phi' P phi */
        d = sat((int64_t)lam_k + sv, p->den_lo, p->den_hi, &c_den);
        /* g = 1 / d     (the one division: acc-width dividend, word divisor, C truncation) */
        if (d <= 0) {
            g = p->g_hi;
            c_div += 1u;
        } else {
            int64_t q = p->dividend / d;
            if (q > p->g_hi) {
                g = p->g_hi;
                c_div += 1u;
            } else {
                g = (int32_t)q;
            }
        }
        /* gc = g c */
        gc = sat(rsh((int64_t)g * c, p->gc_s), p->g_lo, p->g_hi, &c_div);

        th_s = p->theta_s + e;
        /* K h~' has exponent 2e, P~ exponent e */
        P_s = p->P_s + e;
        low = 1;
        for (i = 0; i < n; i++) {
            /* K = P phi / (lambda + phi' P phi) = (g c) h~ */
            const int32_t Ki = sat(rsh((int64_t)h[i] * gc, p->K_s), p->K_lo, p->K_hi, &c_K);
            K[i] = Ki;
            /* theta <- theta + K eps      (K carries the exponent e: shifted out here) */
            theta[i] = sat(theta[i] + rsh((int64_t)Ki * eps, th_s), p->theta_lo,
                           p->theta_hi, &c_th);
            /* low excitation: the information K_i h~_i rounds to zero on the whole diagonal */
            if (rsh((int64_t)Ki * h[i], P_s) != 0) {
                low = 0;
            }
        }
        /* P <- (P - g (P phi)(P phi)') / lambda:  P~ <- P~ - K h~'   upper triangle */
        Pw = P;
        for (i = 0; i < n; i++) {
            const int32_t Ki = K[i];
            for (j = i; j < n; j++) {
                Pw[j - i] = sat(Pw[j - i] - rsh((int64_t)Ki * h[j], P_s), p->P_lo, p->P_hi,
                                &c_P);
            }
            Pw += n - i;
        }
        if (low) {
            flag |= CANRLS_FLAG_LOW_EXCITATION;
        }

        /* c <- c / lambda_k */
        il = (flag & CANRLS_FLAG_WINDUP) ? p->one_lam : p->inv_lam;
        c = sat(rsh((int64_t)c * il, p->c_s), 0, p->lam_hi, &c_P);
        if (c > p->one_lam) {
            if (e > 0) {
                /* c/2 and 2^-e x 2: the words do not move */
                c = rsh32(c, 1);
                e -= 1;
            } else {
                /* fold c into the words: P~ <- c P~, c = 1 */
                for (i = 0; i < CANRLS_TRI(n); i++) {
                    P[i] = sat(rsh((int64_t)P[i] * c, p->c_s), p->P_lo, p->P_hi, &c_P);
                }
                c = p->one_lam;
            }
        }

        /* block exponent: tr P~ fell to tr_hi/2 or below -> shift left by sh, e += sh */
        {
            int64_t tr = 0;
            int64_t trw64 = 0;
            const int32_t *Pii = P;
            for (i = 0; i < n; i++) {
                tr += *Pii;
                trw64 += rsh(*Pii, p->trace_ps);
                Pii += n - i;
            }
            trw = (int32_t)trw64;
            if (tr > 0 && tr <= (p->trace_hi >> 1) && e < p->e_max) {
                int32_t sh = 1;
                while ((tr << (sh + 1)) <= p->trace_hi && e + sh < p->e_max) {
                    sh += 1;
                }
                for (i = 0; i < CANRLS_TRI(n); i++) {
                    P[i] = store(P[i], -sh, p->P_lo, p->P_hi, &c_P);
                }
                e += sh;
                trw = trace_words(S);
            }
        }
        S->e = e;
        S->c = c;
        S->trw = trw;
        applied = 1;
    }

    {
        const uint32_t nsat = c_phi + c_y + c_eps + c_h + c_den + c_div + c_K + c_th + c_P;
        if (nsat > 0u) {
            uint32_t *const cnt = S->counts;
            flag |= CANRLS_FLAG_SATURATION;
            cnt[CANRLS_S_PHI_IN] += c_phi;
            cnt[CANRLS_S_Y_IN] += c_y;
            cnt[CANRLS_S_EPS] += c_eps;
            cnt[CANRLS_S_H] += c_h;
            cnt[CANRLS_S_DEN] += c_den;
            cnt[CANRLS_S_DIV] += c_div;
            cnt[CANRLS_S_K] += c_K;
            cnt[CANRLS_S_THETA] += c_th;
            cnt[CANRLS_S_P] += c_P;
        }
    }
    if (step != NULL) {
        /* tr P = c tr P~, recorded at the scale 2^-(f_P - tr_ps + e) */
        step->eps = eps;
        step->trace = (int32_t)rsh((int64_t)trw * c, p->tc_s);
        step->e = e;
        step->flags = flag;
    }
    return applied;
}
