/*
 * fixed_spec.c -- canrls._fixedspec: the fixed-point RLS as specified, for the host.
 *
 * SPDX-License-Identifier: MIT
 *
 * canrls.estimation.fixed.kernels states the recursion, its integer operations and its
 * plan (the I_* layout of canrls.estimation.fixed.layout); fixed_block() here runs it
 * as stated: every update form (symmetric, literal, naive), any n, 64-bit integers, the
 * equation beside each line. It is not the target's kernel (canrls_fixed.c, symmetric,
 * n <= CANRLS_N_MAX, shaped for a Cortex-M4): FixedRLS runs this one where that one does
 * not apply, and the tests hold the two equal, and both equal to the pure-Python
 * reference of fixed_kernels (reference_block), integer for integer.
 *
 * Integer semantics are those of a DSP: products of two words exact in 64 bits, an
 * arithmetic right shift, and left shifts of negative values as two's complement
 * (written through uint64_t here, where C leaves them undefined). No floating point.
 * The block loop runs without the GIL.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <stdint.h>

#include "pyargs.h"

#if (-1 >> 1) != -1
#error "the specification needs an arithmetic right shift of negative values"
#endif

/* saturation sites, in the order of the counts array (fixed_layout.SITES) */
enum { S_PHI, S_Y, S_EPS, S_H, S_DEN, S_DIV, S_K, S_TH, S_P, S_ACC, NSITES };
/* update forms (fixed_layout.MODE_*) and flag bits (fixed_layout.FLAG_*) */
enum { MODE_SYMMETRIC, MODE_LITERAL, MODE_NAIVE };
enum { FLAG_WINDUP = 1, FLAG_LOW_EXCITATION = 2, FLAG_SATURATION = 4, FLAG_FROZEN = 8 };
/* the plan vector (fixed_layout.I_*) */
enum {
    I_PHI_LO, I_PHI_HI, I_Y_LO, I_Y_HI, I_EPS_LO, I_EPS_HI, I_H_LO, I_H_HI, I_DEN_LO,
    I_DEN_HI, I_G_LO, I_G_HI, I_K_LO, I_K_HI, I_TH_LO, I_TH_HI, I_P_LO, I_P_HI, I_L_LO,
    I_L_HI, I_PHI_PS, I_EPS_TS, I_EPS_OS, I_H_OS, I_S_OS, I_SC_S, I_LAM_D, I_ONE_D,
    I_DIVIDEND, I_GC_S, I_G_UP, I_TH_S, I_P_S, I_INV_LAM, I_ONE_L, I_C_S, I_TR_PS, I_TMAX,
    I_TMAX_LIM, I_TC_S, I_HC_S, I_VW_PS, I_LHS_PS, I_CMP_DF, I_E_MAX, I_TR_HI, I_KG_BL,
    I_KG_MAX, NPARAM
};

#define FRAC_MASK INT64_C(0xFFFFFFFF)
#define HALF_WORD (INT64_C(1) << 31)

/* ---------------------------------------------------------- Q-format arithmetic */
static inline int64_t min64(int64_t a, int64_t b) { return a < b ? a : b; }
static inline int64_t max64(int64_t a, int64_t b) { return a > b ? a : b; }

/* x 2^s for 0 <= s <= 63, two's complement (what the target's shifter gives); the plan
 * keeps every shift in that range, and the count is taken mod 64 as x86-64 does */
static inline int64_t shl(int64_t x, int64_t s)
{
    return (int64_t)((uint64_t)x << (s & 63));
}

/* rounding constant 1 << (s-1) of a right shift by s (0 for s <= 0) */
static inline int64_t half(int64_t s) { return s > 0 ? shl(1, s - 1) : 0; }

/* rounding right shift for 0 <= s <= 62: (x + 2^(s-1)) >> s */
static inline int64_t rsh(int64_t x, int64_t s) { return (x + half(s)) >> s; }

/* x / 2^s rounded half up for s > 0, x itself for s <= 0 */
static inline int64_t round_shift(int64_t x, int64_t s) { return s <= 0 ? x : rsh(x, s); }

/* x clamped to [lo, hi]; *sat = 1 if it was clamped, else 0 */
static inline int64_t saturate(int64_t x, int64_t lo, int64_t hi, int64_t *sat)
{
    const int64_t v = min64(max64(x, lo), hi);
    *sat = v != x;
    return v;
}

/* An accumulator x (scale 2^-(f+s)) stored into a word of scale 2^-f: s >= 0 a
 * rounding right shift then clamp; s < 0 a left shift by -s that clamps before shifting,
 * so it never wraps. */
static inline int64_t store(int64_t x, int64_t s, int64_t lo, int64_t hi, int64_t *sat)
{
    if (s >= 0)
        return saturate(round_shift(x, s), lo, hi, sat);
    *sat = 0;
    if (x == 0)
        return 0;
    const int64_t t = min64(-s, 63);
    /* x 2^t > hi  <=>  x > floor(hi / 2^t) ;  x 2^t < lo  <=>  x < ceil(lo / 2^t) */
    if (x > (hi >> t)) {
        *sat = 1;
        return hi;
    }
    if (x < -((-lo) >> t)) {
        *sat = 1;
        return lo;
    }
    return shl(x, t);
}

/* C division a / b truncated toward zero (b != 0), written as |a| / |b| with the sign */
static inline int64_t div_trunc(int64_t a, int64_t b)
{
    const int64_t q = (a < 0 ? -a : a) / (b < 0 ? -b : b);
    return (a < 0) != (b < 0) ? -q : q;
}

/* The left shift that brings 0 <= m < 2^31 to 30 bits: 30 - bit_length(m), >= 0 */
static inline int64_t norm_shift(int64_t m)
{
    int64_t k = 30;
    while (m > 0) {
        m >>= 1;
        k--;
    }
    return max64(k, 0);
}

/* The 64-bit estimate t 2^32 + f (0 <= f < 2^32) plus the update p 2^-s LSB
 * (0 <= s <= 62) at 2^-32 LSB: floor(p 2^(32-s)) for s < 32; for s >= 32 the high word
 * of the product, floor(p / 2^32) 2^(64-s). Saturated to [lo 2^32, hi 2^32 + 2^32 - 1];
 * *sat = 1 when clamped. */
static inline void theta_add(int64_t *t, int64_t *f, int64_t p, int64_t s, int64_t lo,
                             int64_t hi, int64_t *sat)
{
    const int64_t whole = p >> s; /* floor(p / 2^s): whole LSBs */
    int64_t part;
    if (s >= 32)
        part = shl(p >> 32, 64 - s) & FRAC_MASK; /* the high word below the LSB */
    else
        part = shl(p & (shl(1, s) - 1), 32 - s);
    const int64_t fs = *f + part;
    const int64_t ts = *t + whole + (fs >> 32);
    *sat = 0;
    if (ts > hi) {
        *t = hi;
        *f = FRAC_MASK;
        *sat = 1;
    } else if (ts < lo) {
        *t = lo;
        *f = 0;
        *sat = 1;
    } else {
        *t = ts;
        *f = fs & FRAC_MASK;
    }
}

/* The 64-bit P: V = P~ 2^32 (units of 2^-32 LSB) held as the word W = rsh(V, 32) (P~
 * rounded half up) and the fraction F = V - W 2^32 in [-2^31, 2^31). v_put stores the
 * value w 2^32 + t (any w, t with no overflow) as such a pair: the carry of t moved into
 * the word, then the word clamped to [lo, hi] (the fraction then 2^31 - 1 or -2^31: V
 * clamped to [lo 2^32 - 2^31, hi 2^32 + 2^31 - 1]); *sat = 1 when clamped. */
static inline void v_put(int64_t *W, int64_t *F, int64_t w, int64_t t, int64_t lo, int64_t hi,
                         int64_t *sat)
{
    const int64_t carry = (t + HALF_WORD) >> 32; /* floor((t + 2^31) / 2^32) */
    w += carry;
    t -= shl(carry, 32);
    *sat = 0;
    if (w > hi) {
        *W = hi;
        *F = HALF_WORD - 1;
        *sat = 1;
    } else if (w < lo) {
        *W = lo;
        *F = -HALF_WORD;
        *sat = 1;
    } else {
        *W = w;
        *F = t;
    }
}

/* The decrement u of V for the product p = K_i w~_j shifted by s (0 <= s <= 62), as
 * whole LSBs and the part below (0 <= part < 2^32): u = p 2^(32-s) for s < 32; for
 * s >= 32 the product's high word rounded half up, rsh(p, 32) 2^(64-s). */
static inline void p_dec(int64_t p, int64_t s, int64_t *whole, int64_t *part)
{
    if (s >= 32) {
        const int64_t ph = rsh(p, 32);
        *whole = ph >> (s - 32);
        *part = shl(ph, 64 - s) & FRAC_MASK;
    } else {
        *whole = p >> s;
        *part = shl(p, 32 - s) & FRAC_MASK;
    }
}

/* V <- V - u (p_dec), stored by v_put */
static inline void p_sub(int64_t *W, int64_t *F, int64_t p, int64_t s, int64_t lo, int64_t hi,
                         int64_t *sat)
{
    int64_t whole, part;
    p_dec(p, s, &whole, &part);
    v_put(W, F, *W - whole, *F - part, lo, hi, sat);
}

/* V <- rsh(V c, c_s) for 0 < c, 1 <= c_s <= 31: V c + 2^(c_s-1) = A2 2^32 + Bl exactly
 * (A = W c, B = F c + 2^(c_s-1)), shifted as its two parts */
static inline void p_fold(int64_t *W, int64_t *F, int64_t c, int64_t c_s, int64_t lo,
                          int64_t hi, int64_t *sat)
{
    const int64_t B = *F * c + half(c_s);
    const int64_t A2 = *W * c + (B >> 32);
    const int64_t Bl = B & FRAC_MASK;
    /* rsh(V c, c_s) = (A2 >> c_s) 2^32 + T0, 0 <= T0 < 2^32 */
    const int64_t T0 = shl(A2 & (shl(1, c_s) - 1), 32 - c_s) | (Bl >> c_s);
    v_put(W, F, A2 >> c_s, T0, lo, hi, sat);
}

/* V <- V 2^sh (1 <= sh <= 31), exactly */
static inline void p_shift(int64_t *W, int64_t *F, int64_t sh, int64_t lo, int64_t hi,
                           int64_t *sat)
{
    v_put(W, F, shl(*W, sh), shl(*F, sh), lo, hi, sat);
}

/* ------------------------------------------------------------------- the block */
/* The arrays of one block (fixed_kernels.fixed_block documents each). */
typedef struct {
    Py_ssize_t N, n;
    const int64_t *Phi, *Y;                    /* (N, n), (N,) */
    int64_t *theta, *theta_frac, *P, *P_frac;  /* (n,), (n,), (n, n), (n, n) */
    int64_t *scale;                            /* [e, c] */
    int64_t *work, *counts;                    /* (6, n), (NSITES,) */
    const int64_t *prm;                        /* (NPARAM,) */
    int mode, frozen, record;
    int64_t *eps_out, *theta_out, *trace_out, *exp_out; /* (N,), (N, n), (N,), (N,) */
    uint8_t *flags_out;                        /* (N,) */
} Block;

/* Run the recursion over the rows of the block, in place; the rows applied. */
static Py_ssize_t fixed_block(const Block *B)
{
    const Py_ssize_t n = B->n;
    const int64_t *prm = B->prm;
    int64_t *const theta = B->theta, *const theta_frac = B->theta_frac, *const P = B->P,
                   *const P_frac = B->P_frac;
    int64_t *const phi = B->work, *const phg = B->work + n, *const h = B->work + 2 * n,
                   *const w = B->work + 3 * n, *const K = B->work + 4 * n,
                   *const acc = B->work + 5 * n;
#define PIJ(i, j) P[(i) * n + (j)]
#define FIJ(i, j) P_frac[(i) * n + (j)]
    /* ---- the plan, as locals */
    const int64_t phi_lo = prm[I_PHI_LO], phi_hi = prm[I_PHI_HI], y_lo = prm[I_Y_LO],
                  y_hi = prm[I_Y_HI], eps_lo = prm[I_EPS_LO], eps_hi = prm[I_EPS_HI],
                  h_lo = prm[I_H_LO], h_hi = prm[I_H_HI], den_lo = prm[I_DEN_LO],
                  den_hi = prm[I_DEN_HI], g_lo = prm[I_G_LO], g_hi = prm[I_G_HI],
                  th_lo = prm[I_TH_LO], th_hi = prm[I_TH_HI], P_lo = prm[I_P_LO],
                  P_hi = prm[I_P_HI], l_hi = prm[I_L_HI], phi_ps = prm[I_PHI_PS],
                  eps_ts = prm[I_EPS_TS], eps_os = prm[I_EPS_OS], h_os = prm[I_H_OS],
                  s_os = prm[I_S_OS], sc_s = prm[I_SC_S], lam_d = prm[I_LAM_D],
                  one_d = prm[I_ONE_D], dividend = prm[I_DIVIDEND], gc_s = prm[I_GC_S],
                  g_up = prm[I_G_UP], th_s0 = prm[I_TH_S], P_s0 = prm[I_P_S],
                  inv_lam = prm[I_INV_LAM], one_l = prm[I_ONE_L], c_s = prm[I_C_S],
                  tr_ps = prm[I_TR_PS], tmax = prm[I_TMAX], tmax_lim = prm[I_TMAX_LIM],
                  tc_s = prm[I_TC_S], hc_s = prm[I_HC_S], vw_ps = prm[I_VW_PS],
                  lhs_ps = prm[I_LHS_PS], cmp_df = prm[I_CMP_DF], e_max = prm[I_E_MAX],
                  tr_hi = prm[I_TR_HI], kg_bl = prm[I_KG_BL], kg_max = prm[I_KG_MAX];
    const int symmetric = B->mode == MODE_SYMMETRIC;
    int64_t e = B->scale[0], c = B->scale[1], cc;
    Py_ssize_t applied = 0;
    /* the diagonal of P~ summed >> tr_ps (carried from row to row) */
    int64_t trw = 0;
    for (Py_ssize_t i = 0; i < n; i++)
        trw += rsh(PIJ(i, i), tr_ps);

    for (Py_ssize_t k = 0; k < B->N; k++) {
        /* per-step saturation counts, added to counts once per step */
        int64_t c_phi = 0, c_y = 0, c_eps = 0, c_h = 0, c_den = 0, c_div = 0, c_K = 0,
                c_th = 0, c_P = 0;
        int flag = 0;
        const int64_t *row = B->Phi + k * n;

        /* phi, y <- sat(phi), sat(y)       inputs clamped to their words */
        for (Py_ssize_t j = 0; j < n; j++) {
            const int64_t v = min64(max64(row[j], phi_lo), phi_hi);
            c_phi += v != row[j];
            phi[j] = v;
            /* phi >> ps: the guard bits of the multiply-accumulates */
            phg[j] = rsh(v, phi_ps);
        }
        const int64_t yk = min64(max64(B->Y[k], y_lo), y_hi);
        c_y += yk != B->Y[k];

        /* eps = y - phi' theta */
        int64_t a = eps_ts >= 0 ? shl(yk, eps_ts) : rsh(yk, -eps_ts);
        for (Py_ssize_t j = 0; j < n; j++)
            a -= phg[j] * theta[j];
        const int64_t eps = store(a, eps_os, eps_lo, eps_hi, &cc);
        c_eps += cc;

        if (B->frozen) {
            flag = FLAG_FROZEN;
            for (Py_ssize_t i = 0; i < n; i++)
                K[i] = 0;
        } else {
            if (symmetric) {
                /* h~ = P~ phi   (P~_ij read from the upper triangle only) */
                for (Py_ssize_t i = 0; i < n; i++)
                    acc[i] = 0;
                for (Py_ssize_t i = 0; i < n; i++) {
                    const int64_t pi_ = phg[i];
                    /* h_i = sum_{j<i} P_ji phi_j (scattered by the rows above) + P_ii phi_i */
                    a = acc[i] + PIJ(i, i) * pi_;
                    for (Py_ssize_t j = i + 1; j < n; j++) {
                        const int64_t Pij = PIJ(i, j);
                        /* P_ij phi_j -> h_i ;  P_ji phi_i = P_ij phi_i -> h_j */
                        a += Pij * phg[j];
                        acc[j] += Pij * pi_;
                    }
                    h[i] = w[i] = store(a, h_os, h_lo, h_hi, &cc);
                    c_h += cc;
                }
            } else {
                /* h~ = P~ phi (rows): P~ may have lost its symmetry */
                for (Py_ssize_t i = 0; i < n; i++) {
                    a = 0;
                    for (Py_ssize_t j = 0; j < n; j++)
                        a += PIJ(i, j) * phg[j];
                    h[i] = w[i] = store(a, h_os, h_lo, h_hi, &cc);
                    c_h += cc;
                }
                if (B->mode == MODE_LITERAL) {
                    /* w~ = P~' phi (columns), i.e. the row phi' P~ as written */
                    for (Py_ssize_t i = 0; i < n; i++)
                        acc[i] = 0;
                    for (Py_ssize_t j = 0; j < n; j++)
                        for (Py_ssize_t i = 0; i < n; i++)
                            acc[i] += PIJ(j, i) * phg[j];
                    for (Py_ssize_t i = 0; i < n; i++) {
                        w[i] = store(acc[i], h_os, h_lo, h_hi, &cc);
                        c_h += cc;
                    }
                }
            }

            /* s~ = phi' h~, brought from the scale of P (exponent e) to that of lambda */
            a = 0;
            for (Py_ssize_t i = 0; i < n; i++)
                a += phg[i] * h[i];
            const int64_t st = store(rsh(a, e), s_os, den_lo, den_hi, &cc);
            c_den += cc;
            /* s = phi' P phi = c s~ */
            const int64_t sv = saturate(rsh(st * c, sc_s), den_lo, den_hi, &cc);
            c_den += cc;

            /* windup <=> (tr P - g h'w)/lambda > trace_max
             *        <=> (tr P - lambda trace_max) (lambda + phi'P phi) > h'w */
            int64_t lam_k = lam_d;
            if (tmax <= (tmax_lim >> e)) {
                /* tr P = c tr P~   (trw: the diagonal summed >> tr_ps, kept from the last row) */
                const int64_t T = rsh(trw * c, tc_s) - shl(tmax, e);
                if (T > 0) {
                    const int64_t d_lam = saturate(lam_d + sv, den_lo, den_hi, &cc);
                    int64_t a_vw = 0;
                    for (Py_ssize_t i = 0; i < n; i++) {
                        /* h = c h~ ; w = c w~ */
                        const int64_t hi_ = rsh(h[i] * c, hc_s);
                        const int64_t wi_ = rsh(w[i] * c, hc_s);
                        a_vw += rsh(hi_ * wi_, vw_ps);
                    }
                    const int64_t lhs = rsh(min64(T, P_hi) * d_lam, lhs_ps);
                    /* the two sides differ in scale by cmp_df - e bits */
                    const int64_t df = cmp_df - e;
                    const int up = df >= 0 ? (lhs >> min64(df, 63)) > a_vw
                                           : lhs > (a_vw >> min64(-df, 63));
                    if (up) {
                        lam_k = one_d;
                        flag = FLAG_WINDUP;
                    }
                }
            }

            /* d = lambda_k + phi' P phi */
            const int64_t d = saturate(lam_k + sv, den_lo, den_hi, &cc);
            c_den += cc;
            /* g = 1 / d     (the one division: acc-width dividend, word divisor, C truncation),
             * normalised: g 2^kg = DIVIDEND 2^kg / d, kg = bit_length(d) - kg_bl within
             * [0, kg_max] and the room of the shifts below (kg = 0 for d < 2) */
            int64_t g, kg = 0;
            if (d <= 0) {
                g = g_hi;
                c_div += 1;
            } else {
                int64_t bl = 0;
                while (bl < 63 && (d >> bl) != 0)
                    bl++;
                kg = max64(0, min64(min64(bl - kg_bl, kg_max),
                                    min64(62 - P_s0 - e, 62 - th_s0 - e)));
                g = div_trunc(shl(dividend, kg), d);
                if (g > g_hi) {
                    g = g_hi;
                    c_div += 1;
                }
            }
            /* gc = g c */
            const int64_t gc = saturate(rsh(g * c, gc_s), g_lo, g_hi, &cc);
            c_div += cc;

            /* normalisation of the updates (once per step): h~, w~ and eps shifted left
             * (exactly) to 31 bits, so that the theta and P updates take the high word
             * of their products */
            int64_t m = 0;
            for (Py_ssize_t i = 0; i < n; i++) {
                m |= h[i] ^ (h[i] >> 63);
                m |= w[i] ^ (w[i] >> 63);
            }
            int64_t kn = norm_shift(m);
            kn = min64(min64(kn, (62 - P_s0 - e - kg) >> 1), 62 - th_s0 - e - kg);
            const int64_t ke = min64(norm_shift(eps ^ (eps >> 63)), 62 - th_s0 - e - kn - kg);
            const int64_t epn = shl(eps, ke);
            const int64_t gcn = shl(gc, g_up);
            const int64_t th_s = th_s0 + e + kn + ke + kg;
            /* K h~' has exponent 2e, P~ exponent e; K and h~ carry 2^kn each, g 2^kg */
            const int64_t P_s = P_s0 + e + 2 * kn + kg;
            int low = 1;
            for (Py_ssize_t i = 0; i < n; i++) {
                h[i] = shl(h[i], kn);
                w[i] = shl(w[i], kn);
            }
            for (Py_ssize_t i = 0; i < n; i++) {
                /* K = P phi / (lambda + phi' P phi) = (g c) h~: the high word, rounded */
                const int64_t Ki = (h[i] * gcn + shl(1, 31)) >> 32;
                K[i] = Ki;
                /* theta:theta_frac <- theta:theta_frac + K eps   (64 bits: K eps floored
                 * to 2^-32 LSB; K carries the exponent e + kn: shifted out here) */
                theta_add(&theta[i], &theta_frac[i], Ki * epn, th_s, th_lo, th_hi, &cc);
                c_th += cc;
                /* low excitation: the decrement of the information K_i w~_i is zero (at
                 * 2^-32 LSB) on the whole diagonal */
                int64_t whole, part;
                p_dec(Ki * w[i], P_s, &whole, &part);
                if (whole != 0 || part != 0)
                    low = 0;
            }
            if (symmetric) {
                /* P <- (P - g (P phi)(P phi)') / lambda:  P~ <- P~ - K h~'   upper triangle,
                 * in 64 bits: V <- V - u (p_dec) */
                for (Py_ssize_t i = 0; i < n; i++)
                    for (Py_ssize_t j = i; j < n; j++) {
                        p_sub(&PIJ(i, j), &FIJ(i, j), K[i] * h[j], P_s, P_lo, P_hi, &cc);
                        c_P += cc;
                    }
            } else {
                /* P <- (P - K phi' P) / lambda:  P~ <- P~ - K w~', full matrix as written
                 * (naive: w~ = h~, the row phi' P taken as (P phi)') */
                for (Py_ssize_t i = 0; i < n; i++)
                    for (Py_ssize_t j = 0; j < n; j++) {
                        p_sub(&PIJ(i, j), &FIJ(i, j), K[i] * w[j], P_s, P_lo, P_hi, &cc);
                        c_P += cc;
                    }
            }
            if (low)
                flag |= FLAG_LOW_EXCITATION;

            /* c <- c / lambda_k */
            const int64_t il = (flag & FLAG_WINDUP) ? one_l : inv_lam;
            c = saturate(rsh(c * il, c_s), 0, l_hi, &cc);
            c_P += cc;
            if (c > one_l) {
                if (e > 0) {
                    /* c/2 and 2^-e x 2: the words do not move */
                    c = rsh(c, 1);
                    e -= 1;
                } else {
                    /* fold c into the words: P~ <- c P~ (V <- rsh(V c, c_s)), c = 1 */
                    for (Py_ssize_t i = 0; i < n; i++)
                        for (Py_ssize_t j = symmetric ? i : 0; j < n; j++) {
                            p_fold(&PIJ(i, j), &FIJ(i, j), c, c_s, P_lo, P_hi, &cc);
                            c_P += cc;
                        }
                    c = one_l;
                }
            }

            /* block exponent: tr P~ fell to tr_hi/2 or below -> shift left by sh, e += sh */
            int64_t tr = 0;
            trw = 0;
            for (Py_ssize_t i = 0; i < n; i++) {
                tr += PIJ(i, i);
                trw += rsh(PIJ(i, i), tr_ps);
            }
            if (tr > 0 && tr <= (tr_hi >> 1) && e < e_max) {
                int64_t sh = 1;
                while (shl(tr, sh + 1) <= tr_hi && e + sh < e_max)
                    sh++;
                /* V <- V 2^sh (the words and their fractions) */
                for (Py_ssize_t i = 0; i < n; i++)
                    for (Py_ssize_t j = symmetric ? i : 0; j < n; j++) {
                        p_shift(&PIJ(i, j), &FIJ(i, j), sh, P_lo, P_hi, &cc);
                        c_P += cc;
                    }
                e += sh;
                trw = 0;
                for (Py_ssize_t i = 0; i < n; i++)
                    trw += rsh(PIJ(i, i), tr_ps);
            }
            B->scale[0] = e;
            B->scale[1] = c;
            applied++;
        }

        const int64_t nsat = c_phi + c_y + c_eps + c_h + c_den + c_div + c_K + c_th + c_P;
        if (nsat > 0) {
            flag |= FLAG_SATURATION;
            B->counts[S_PHI] += c_phi;
            B->counts[S_Y] += c_y;
            B->counts[S_EPS] += c_eps;
            B->counts[S_H] += c_h;
            B->counts[S_DEN] += c_den;
            B->counts[S_DIV] += c_div;
            B->counts[S_K] += c_K;
            B->counts[S_TH] += c_th;
            B->counts[S_P] += c_P;
        }
        /* tr P = c tr P~, recorded at the scale 2^-(f_P - tr_ps + e) */
        B->eps_out[k] = eps;
        B->trace_out[k] = rsh(trw * c, tc_s);
        B->exp_out[k] = e;
        B->flags_out[k] = (uint8_t)flag;
        if (B->record)
            for (Py_ssize_t i = 0; i < n; i++)
                B->theta_out[k * n + i] = theta[i];
    }
#undef PIJ
#undef FIJ
    return applied;
}

/* ================================================================= Python glue */
PyDoc_STRVAR(fixed_block_doc,
"fixed_block(Phi, Y, theta, theta_frac, P, P_frac, scale, work, counts, prm, mode, frozen,\n"
"            record, eps_out, theta_out, trace_out, exp_out, flags_out) -> applied\n"
"--\n\n"
"Run the fixed-point recursion over the rows of Phi, in place\n"
"(canrls.estimation.fixed.kernels.fixed_block documents every argument).");

static PyObject *py_fixed_block(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)self;
    static const Spec spec[] = {
        {0, "Phi", I64, 2, RO}, {1, "Y", I64, 1, RO}, {2, "theta", I64, 1, RW},
        {3, "theta_frac", I64, 1, RW}, {4, "P", I64, 2, RW}, {5, "P_frac", I64, 2, RW},
        {6, "scale", I64, 1, RW}, {7, "work", I64, 2, RW}, {8, "counts", I64, 1, RW},
        {9, "prm", I64, 1, RO}, {13, "eps_out", I64, 1, RW}, {14, "theta_out", I64, 2, RW},
        {15, "trace_out", I64, 1, RW}, {16, "exp_out", I64, 1, RW},
        {17, "flags_out", U8, 1, RW},
    };
    Args a = {.fn = "fixed_block", .count = 0};
    Py_buffer *b[COUNT(spec)];
    int64_t mode;
    int frozen, record;
    PyObject *res = NULL;
    if (!start(&a, nargs, 18) || !as_int64(args[10], &mode) || !as_bool(args[11], &frozen)
        || !as_bool(args[12], &record))
        return NULL;
    if (mode != MODE_SYMMETRIC && mode != MODE_LITERAL && mode != MODE_NAIVE) {
        PyErr_Format(PyExc_ValueError, "fixed_block: unknown mode %lld", (long long)mode);
        return NULL;
    }
    if (take(&a, args, spec, COUNT(spec), b, I64)) {
        const Py_ssize_t n = dim(b[2], 0), N = dim(b[0], 0);
        if (need(&a, b[0], "Phi", N, n) && need(&a, b[1], "Y", N, -1)
            && need(&a, b[3], "theta_frac", n, -1) && need(&a, b[4], "P", n, n)
            && need(&a, b[5], "P_frac", n, n) && need(&a, b[6], "scale", 2, -1)
            && need(&a, b[7], "work", 6, n) && need(&a, b[8], "counts", NSITES, -1)
            && need(&a, b[9], "prm", NPARAM, -1) && need(&a, b[10], "eps_out", N, -1)
            && need(&a, b[11], "theta_out", record ? N : dim(b[11], 0), n)
            && need(&a, b[12], "trace_out", N, -1) && need(&a, b[13], "exp_out", N, -1)
            && need(&a, b[14], "flags_out", N, -1)) {
            const Block B = {.N = N, .n = n, .Phi = I(b[0]), .Y = I(b[1]), .theta = I(b[2]),
                             .theta_frac = I(b[3]), .P = I(b[4]), .P_frac = I(b[5]),
                             .scale = I(b[6]), .work = I(b[7]), .counts = I(b[8]),
                             .prm = I(b[9]), .mode = (int)mode, .frozen = frozen,
                             .record = record, .eps_out = I(b[10]), .theta_out = I(b[11]),
                             .trace_out = I(b[12]), .exp_out = I(b[13]),
                             .flags_out = U(b[14])};
            Py_ssize_t applied;
            Py_BEGIN_ALLOW_THREADS
            applied = fixed_block(&B);
            Py_END_ALLOW_THREADS
            res = PyLong_FromSsize_t(applied);
        }
    }
    release(&a);
    return res;
}

/* ------------------------------------------------ the Q primitives, for the tests */
/* The integer arguments of a primitive (ValueError when a shift is out of its range). */
static int int_args(const char *fn, PyObject *const *args, Py_ssize_t nargs, Py_ssize_t want,
                    int64_t *x)
{
    if (nargs != want) {
        PyErr_Format(PyExc_TypeError, "%s() takes %zd arguments (%zd given)", fn, want, nargs);
        return 0;
    }
    for (Py_ssize_t k = 0; k < want; k++)
        if (!as_int64(args[k], &x[k]))
            return 0;
    return 1;
}

static PyObject *pair(int64_t v, int64_t sat) { return Py_BuildValue("(LL)", v, sat); }

PyDoc_STRVAR(round_shift_doc, "round_shift(x, s) -> x / 2**s rounded half up (s <= 62)");
static PyObject *py_round_shift(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)self;
    int64_t x[2];
    if (!int_args("round_shift", args, nargs, 2, x))
        return NULL;
    if (x[1] > 62)
        return PyErr_Format(PyExc_ValueError, "round_shift: s = %lld > 62", (long long)x[1]);
    return PyLong_FromLongLong(round_shift(x[0], x[1]));
}

PyDoc_STRVAR(saturate_doc, "saturate(x, lo, hi) -> (x clamped to [lo, hi], clamped)");
static PyObject *py_saturate(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)self;
    int64_t x[3], sat;
    if (!int_args("saturate", args, nargs, 3, x))
        return NULL;
    const int64_t v = saturate(x[0], x[1], x[2], &sat);
    return pair(v, sat);
}

PyDoc_STRVAR(store_doc, "store(x, s, lo, hi) -> (word, saturated): the accumulator x at "
                        "2^-(f+s) stored into a word at 2^-f (s <= 62)");
static PyObject *py_store(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)self;
    int64_t x[4], sat;
    if (!int_args("store", args, nargs, 4, x))
        return NULL;
    if (x[1] > 62 || x[2] < -(INT64_C(1) << 62) || x[3] < x[2])
        return PyErr_Format(PyExc_ValueError, "store: s = %lld > 62 or a wrong range",
                            (long long)x[1]);
    const int64_t v = store(x[0], x[1], x[2], x[3], &sat);
    return pair(v, sat);
}

PyDoc_STRVAR(sat_mul_doc, "sat_mul(a, b, s, lo, hi) -> (word, saturated): the product of "
                          "two words stored with output shift s");
static PyObject *py_sat_mul(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)self;
    int64_t x[5], sat;
    if (!int_args("sat_mul", args, nargs, 5, x))
        return NULL;
    const int64_t word = INT64_C(1) << 32;
    if (x[0] < -word || x[0] > word || x[1] < -word || x[1] > word || x[2] > 62
        || x[3] < -(INT64_C(1) << 62) || x[4] < x[3])
        return PyErr_SetString(PyExc_ValueError, "sat_mul: a and b must be words, s <= 62"),
               NULL;
    const int64_t v = store(x[0] * x[1], x[2], x[3], x[4], &sat);
    return pair(v, sat);
}

PyDoc_STRVAR(sat_add_doc, "sat_add(a, b, lo, hi) -> (a + b clamped, clamped); |a|, |b| < 2**62");
static PyObject *py_sat_add(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)self;
    int64_t x[4], sat;
    if (!int_args("sat_add", args, nargs, 4, x))
        return NULL;
    const int64_t lim = INT64_C(1) << 62;
    if (x[0] < -lim || x[0] > lim || x[1] < -lim || x[1] > lim)
        return PyErr_SetString(PyExc_ValueError, "sat_add: |a|, |b| must be <= 2**62"), NULL;
    const int64_t v = saturate(x[0] + x[1], x[2], x[3], &sat);
    return pair(v, sat);
}

PyDoc_STRVAR(div_trunc_doc, "div_trunc(a, b) -> C's a / b, truncated toward zero (b != 0)");
static PyObject *py_div_trunc(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)self;
    int64_t x[2];
    if (!int_args("div_trunc", args, nargs, 2, x))
        return NULL;
    if (x[1] == 0 || x[0] == INT64_MIN || x[1] == INT64_MIN)
        return PyErr_SetString(PyExc_ValueError, "div_trunc: b = 0 or an operand is -2**63"),
               NULL;
    return PyLong_FromLongLong(div_trunc(x[0], x[1]));
}

/* ================================================================== module */
#define FASTCALL(name) \
    {#name, (PyCFunction)(void (*)(void))py_##name, METH_FASTCALL, name##_doc}
static PyMethodDef methods[] = {
    FASTCALL(fixed_block), FASTCALL(round_shift), FASTCALL(saturate), FASTCALL(store),
    FASTCALL(sat_mul),     FASTCALL(sat_add),     FASTCALL(div_trunc),
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT,
    .m_name = "canrls._fixedspec",
    .m_doc = "The fixed-point RLS as specified, every form, any n (C, see "
             "src/canrls/c/host/fixed_spec.c).",
    .m_size = 0,
    .m_methods = methods,
};

PyMODINIT_FUNC PyInit__fixedspec(void)
{
    PyObject *m = PyModule_Create(&module);
    if (!m)
        return NULL;
    if (PyModule_AddIntConstant(m, "NSITES", NSITES) < 0
        || PyModule_AddIntConstant(m, "NPARAM", NPARAM) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
