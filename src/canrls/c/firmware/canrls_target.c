/*
 * canrls_target.c -- the whole estimator on the target (see canrls_target.h).
 *
 * SPDX-License-Identifier: MIT
 *
 * Each function is the one of the same name (without cr_ / canrls_target_) in
 * src/canrls/firmware/qmath.py and spec.py, line for line. Integers only; a left shift
 * is never applied to a negative value (a multiplication by a power of two instead),
 * and the arithmetic right shift of a negative value is required (checked below).
 */
#include "canrls_target.h"

#include <string.h>

#include "canrls_target_check.h"

#include "canrls_target_math.h"

/* an arithmetic right shift of negative values (every compiler for these targets has one) */
typedef char canrls_target_needs_arithmetic_shift[((-8) >> 1) == -4 ? 1 : -1];

/* ------------------------------------------------------------------ arithmetic
 * (the per-frame path's: canrls_target_math.h) */

/* The rare steps' helpers and 64-bit shifts (the rescale, the publication): out of line
 * when built for size (CANRLS_SMALL: a call is shorter than a two-word shift), else the
 * compiler's choice. */
#if CANRLS_SMALL && defined(__GNUC__)
#define CR_RARE static __attribute__((noinline))
#else
#define CR_RARE static
#endif

/* x 2^s, 0 <= s <= 63 (the caller bounds the result) */
CR_RARE int64_t cr_lsl64(int64_t x, int32_t s)
{
    return (int64_t)((uint64_t)x << s);
}

/* floor(x / 2^s), 0 <= s <= 63 */
CR_RARE int64_t cr_asr64(int64_t x, int32_t s)
{
    return x >> s;
}

/* floor(x / 2^s) of an unsigned x, 0 <= s <= 63 */
CR_RARE uint64_t cr_lsr64(uint64_t x, int32_t s)
{
    return x >> s;
}

CR_RARE int32_t cr_bitlen64(uint64_t v)
{
#if defined(__GNUC__)
    /* one CLZ of the high word, or of the low word */
    const uint32_t hi = (uint32_t)(v >> 32), lo = (uint32_t)v;
    return hi != 0u ? 64 - __builtin_clz(hi) : lo != 0u ? 32 - __builtin_clz(lo) : 0;
#else
    int32_t n = 0;
    while (v != 0u) {
        v >>= 1;
        n++;
    }
    return n;
#endif
}

/* clog2(n) = bit length of n - 1 (n >= 1) */
static int32_t cr_clog2(uint64_t n)
{
    return cr_bitlen64(n - 1u);
}

/* clog2(a m) of a product of up to 92 bits: a < 2^61, m < 2^31, a m >= 1 */
static int32_t cr_clog2_mul(uint64_t a, uint32_t m)
{
    /* a m = A 2^31 + B, A = (a >> 31) m, B = (a mod 2^31) m ; as hi 2^32 + lo */
    const uint64_t A = (a >> 31) * m;
    const uint64_t B = (a & 0x7FFFFFFFu) * m;
    uint64_t lo = ((A & 1u) << 31) + (B & 0xFFFFFFFFu);
    uint64_t hi = (A >> 1) + (B >> 32) + (lo >> 32);
    lo &= 0xFFFFFFFFu;
    /* n - 1 */
    if (lo == 0u) {
        hi -= 1u;
        lo = 0xFFFFFFFFu;
    } else {
        lo -= 1u;
    }
    return hi != 0u ? 32 + cr_bitlen64(hi) : cr_bitlen64(lo);
}

/* floor(sqrt(n)), n >= 0, bit by bit */
CR_RARE int64_t cr_isqrt(int64_t n)
{
    uint64_t v = (uint64_t)n, r = 0u, bit = (uint64_t)1 << 62;
    while (bit > v) {
        bit >>= 2;
    }
    while (bit != 0u) {
        if (v >= r + bit) {
            v -= r + bit;
            r = (r >> 1) + bit;
        } else {
            r >>= 1;
        }
        bit >>= 2;
    }
    return (int64_t)r;
}

/* the binary32 bits of v 2^e, round half to even, saturated at 3.4e38; |v| < 2^32 */
static uint32_t cr_f32_bits(int64_t v, int32_t e)
{
    const uint32_t sat_bits = 0x7F7FC99Eu;
    uint32_t sign, bits;
    uint64_t a, m;
    int32_t q, s;
    if (v == 0) {
        return 0u;
    }
    sign = v < 0 ? 0x80000000u : 0u;
    a = v < 0 ? 0u - (uint64_t)v : (uint64_t)v;
    q = cr_bitlen64(a) - 1 + e - 23;
    q = q < -149 ? -149 : q;
    s = q - e;
    if (s > 0) {
        if (s > 33) {
            m = 0u;
        } else {
            const uint64_t rem = a & ((uint64_t)cr_lsl64(1, s) - 1u);
            const uint64_t half = (uint64_t)cr_lsl64(1, s - 1);
            m = cr_lsr64(a, s);
            if (rem > half || (rem == half && (m & 1u) != 0u)) {
                m += 1u;
            }
        }
    } else {
        m = (uint64_t)cr_lsl64((int64_t)a, -s);
    }
    if ((m >> 24) != 0u) {
        m >>= 1;
        q += 1;
    }
    if ((m >> 23) != 0u) {
        const int32_t biased = q + 150;
        bits = biased < 255 ? ((uint32_t)biased << 23) | (uint32_t)(m & 0x7FFFFFu) : sat_bits + 1u;
    } else {
        bits = (uint32_t)m;
    }
    if (bits > sat_bits) {
        bits = sat_bits;
    }
    return sign | bits;
}

/* ------------------------------------------------------------------ frames in */

#ifndef CANRLS_FRONT
/* the raw value of a field (sign-extended, less its bias) from the payload's words */
static int32_t cr_extract(const canrls_field *f, uint64_t le, uint64_t be)
{
    /* raw = (word >> shift) mod 2^length */
    const uint32_t acc = (uint32_t)((f->big_endian ? be : le) >> f->shift)
                         & (0xFFFFFFFFu >> (32u - f->length));
    if (f->is_signed && ((acc >> (f->length - 1u)) & 1u) != 0u) {
        /* two's complement: the bits above the field set */
        return (int32_t)(acc | ~(0xFFFFFFFFu >> (32u - f->length)));
    }
    return f->biased ? (int32_t)(acc ^ 0x80000000u) : (int32_t)acc;
}

/* a float field's value in fixed point (cr_float_word) */
static int cr_float(const canrls_field *f, uint64_t le, uint64_t be, int32_t *v)
{
    return cr_float_word((f->big_endian ? be : le) >> f->shift, f->length == 64u, f->frac, v);
}
#endif /* CANRLS_FRONT */

/* ------------------------------------------------------------------ set-up */

/* the trace bound: the sum of the columns' terms (saturating), at most the cap */
static int32_t cr_trace_bound(const canrls_equation *e, const canrls_target_eq *q)
{
    int64_t sum = 0;
    uint32_t j;
    if (!e->trace_follows) {
        return e->plan->trace_max_lam;
    }
    for (j = 0; j < e->n; j++) {
        sum = sum > I62 - q->terms[j] ? I62 : sum + q->terms[j];
    }
    return (int32_t)(sum < e->trace_cap ? sum : e->trace_cap);
}

int32_t canrls_target_trace_bound(const canrls_equation *e, const canrls_target_eq *q)
{
    return cr_trace_bound(e, q);
}

int canrls_target_init(canrls_target *S, const canrls_target_model *M)
{
    uint32_t i, j;
    if (S == NULL || M == NULL || M->nmsg > CANRLS_TARGET_MSG_MAX
        || M->nfilters > CANRLS_TARGET_FILTER_MAX || M->neq > CANRLS_TARGET_EQ_MAX
        || M->neq < 1u) {
        return CANRLS_EINVAL;
    }
    memset(S, 0, sizeof *S);
    S->model = M;
    for (i = 0; i < M->nmsg; i++) {
        S->last_counter[i] = -1;
    }
    S->open_counter = -1;
    for (i = 0; i < M->nfilters; i++) {
        if (M->filters[i].kind == CANRLS_SRC_CONST) {
            /* F[1] = 1 exactly, sF[1] = 0: the constant needs no filter */
            S->x1[i] = cr_shl(ONE_Q30, M->filters[i].fx);
            S->primed[i] = 1u;
        }
    }
    for (i = 0; i < M->neq; i++) {
        const canrls_equation *e = &M->equations[i];
        canrls_target_eq *q = &S->eq[i];
        if (e->n > CANRLS_N_MAX) {
            return CANRLS_EINVAL;
        }
        for (j = 0; j < e->n; j++) {
            q->sh[j] = e->columns[j].sh;
            q->exponents[j] = e->columns[j].exponent;
            q->pending[j] = e->columns[j].pending;
            q->ridge[j] = e->ridge[j];
            q->terms[j] = e->trace_terms[j];
        }
        q->sh_y = e->output.sh;
        q->exponents[e->n] = e->output.exponent;
        q->pending_y = e->output.pending;
        {
            /* q->plan = *e->plan, byte by byte: the estimator calls no memcpy (libc's
             * takes 308 B at -Os, for one copy at the start) */
            const unsigned char *from = (const unsigned char *)e->plan;
            unsigned char *to = (unsigned char *)&q->plan;
            for (j = 0; j < sizeof q->plan; j++) {
                to[j] = from[j];
            }
        }
        q->plan.trace_max_lam = cr_trace_bound(e, q);
        if (canrls_init_q31(&q->rls, &q->plan, e->n, e->p0, e->e0) != CANRLS_OK) {
            return CANRLS_EINVAL;
        }
    }
    return CANRLS_OK;
}

/* ------------------------------------------------------------------ one sample */

/* X + O of a column */
static int64_t cr_state(const canrls_target *S, const canrls_column *c)
{
    return (c->derivative ? S->x2[c->filter] : S->x1[c->filter]) + c->offset;
}

#ifndef CANRLS_FRONT
/* the input u of every filter of the bank */
static void cr_inputs(const canrls_target *S, int32_t *u)
{
    const canrls_target_model *M = S->model;
    int64_t z = 0, r = 0;
    uint64_t ph = 0u;
    uint32_t i;
    if (M->tanh_m != 0) {
        /* z = w / band, Q24 */
        z = cr_sat(cr_rsh((int64_t)S->raw[CANRLS_SPEED] * M->tanh_m + M->tanh_b, M->tanh_sh),
                   INT32_MIN, INT32_MAX);
    }
    if (M->strib_m != 0) {
        /* r = w / ws, Q24 */
        r = cr_sat(cr_rsh((int64_t)S->raw[CANRLS_SPEED] * M->strib_m + M->strib_b, M->strib_sh),
                   INT32_MIN, INT32_MAX);
    }
    if (M->phase_m != 0u) {
        /* phase = raw PM + PO, turns in Q64 (modulo one turn) */
        ph = (uint64_t)(int64_t)S->raw[CANRLS_POSITION] * M->phase_m + M->phase_o;
    }
    for (i = 0; i < M->nfilters; i++) {
        const canrls_filter *f = &M->filters[i];
        switch (f->kind) {
        case CANRLS_SRC_RAW:
            u[i] = S->raw[f->role];
            break;
        case CANRLS_SRC_TANH:
            /* tanh(w / band) */
            u[i] = cr_tanh_q24((int32_t)z);
            break;
        case CANRLS_SRC_STRIBECK: {
            /* x = (w / ws)^2, Q24, at most 32 ; tanh(w / band) exp(-(w / ws)^2) */
            int64_t x = cr_rsh(r * r, 24);
            x = x < ((int64_t)32 << 24) ? x : (int64_t)32 << 24;
            u[i] = (int32_t)cr_rsh((int64_t)cr_tanh_q24((int32_t)z) * cr_exp_neg_q24(x), 30);
            break;
        }
        case CANRLS_SRC_SIN:
        case CANRLS_SRC_COS: {
            /* sin, cos of k theta: the phase times k, modulo one turn */
            int32_t s, c;
            cr_sincos_q64((uint64_t)f->order * ph, &s, &c);
            u[i] = f->kind == CANRLS_SRC_SIN ? s : c;
            break;
        }
        default:
            u[i] = 0; /* the constant: no input */
            break;
        }
    }
}

/* advance every filter of the bank by one sample */
static void cr_filter(canrls_target *S, const int32_t *u)
{
    const canrls_target_model *M = S->model;
    uint32_t i;
    for (i = 0; i < M->nfilters; i++) {
        const canrls_filter *f = &M->filters[i];
        const int32_t *g = M->G[f->hold];
        int32_t uh, ul;
        int64_t x1, x2;
        if (f->kind == CANRLS_SRC_CONST) {
            continue;
        }
        cr_split_input(u[i], f->fx, &uh, &ul);
        if (!S->primed[i]) {
            /* at rest on the first sample: x = [u 2^FX, 0] */
            S->x1[i] = cr_shl(u[i], f->fx);
            S->x2[i] = 0;
            S->uph[i] = uh;
            S->upl[i] = ul;
            S->primed[i] = 1u;
            continue;
        }
        x1 = S->x1[i];
        x2 = S->x2[i];
        /* x1 = A00 x1 + A01 x2 + (G0_1 u[k-1] + G1_1 u[k]) 2^FX, Q30 coefficients */
        S->x1[i] = cr_svf_row(M->A[0], M->A[1], g[0], g[2], x1, x2, S->uph[i], S->upl[i], uh, ul);
        /* x2 = A10 x1 + A11 x2 + (G0_2 u[k-1] + G1_2 u[k]) 2^FX   (x2 = sF[u] T 2^FX) */
        S->x2[i] = cr_svf_row(M->A[2], M->A[3], g[1], g[3], x1, x2, S->uph[i], S->upl[i], uh, ul);
        if (cr_narrow(f)) {
            /* 32-bit states: saturated to int32 */
            S->x1[i] = cr_sat32(S->x1[i]);
            S->x2[i] = cr_sat32(S->x2[i]);
        }
        S->uph[i] = uh;
        S->upl[i] = ul;
    }
}
#endif /* CANRLS_FRONT */

void canrls_target_restart(canrls_target *S)
{
    const canrls_target_model *M = S->model;
    uint32_t i;
    for (i = 0; i < M->nfilters; i++) {
        if (M->filters[i].kind != CANRLS_SRC_CONST) {
            S->primed[i] = 0u;
        }
    }
    for (i = 0; i < M->neq; i++) {
        S->eq[i].left = M->equations[i].warmup;
        S->eq[i].w_last = 0;
    }
}

/* cr_rsh of the rare steps */
static int64_t cr_rsh64(int64_t x, int32_t s)
{
    if (s <= 0) {
        return x;
    }
    return s >= 64 ? 0 : (cr_asr64(x, s - 1) + 1) >> 1;
}

/* the kernel's state: theta (words, fractions) and P (words, fractions) */
static void cr_read(const canrls_target_eq *q, uint32_t n, int32_t *theta, uint32_t *frac,
                    int32_t *P, int32_t *P_frac)
{
    uint32_t k;
    for (k = 0; k < n; k++) {
        theta[k] = canrls_theta_q31(&q->rls, k);
        frac[k] = canrls_theta_frac_q31(&q->rls, k);
    }
    for (k = 0; k < CANRLS_TRI(n); k++) {
        P[k] = canrls_P_q31(&q->rls, k);
        P_frac[k] = canrls_P_frac_q31(&q->rls, k);
    }
}

/* the kernel continues from its state in new words (canrls_restore_q31); with a new
 * trace bound the plan changes, so it is initialised again first (counters and
 * `frozen` kept) */
static void cr_restore(canrls_target_eq *q, const canrls_equation *e, const int32_t *theta,
                       const uint32_t *frac, const int32_t *P, const int32_t *P_frac,
                       int32_t ex, int replan)
{
    uint32_t counts[CANRLS_NSITES];
    const int32_t c = q->rls.c;
    const uint32_t frozen = q->rls.frozen;
    if (replan) {
        memcpy(counts, q->rls.counts, sizeof counts);
        q->plan.trace_max_lam = cr_trace_bound(e, q);
        (void)canrls_init_q31(&q->rls, &q->plan, e->n, e->p0, e->e0);
        memcpy(q->rls.counts, counts, sizeof counts);
        q->rls.frozen = frozen;
    }
    (void)canrls_restore_q31(&q->rls, theta, frac, P, P_frac, ex, c);
}

/* V 2^s, V = P~ 2^32 the 64-bit element (word w, fraction f), exactly for s > 0 and
 * rsh(V, -s) for s < 0, into the word rsh(V', 32) and the fraction V' - word 2^32;
 * saturated where the word leaves [lo, hi] (counted in *n). V itself may lie just below
 * -2^63 (w = INT32_MIN, f < 0), so it is never formed in one int64_t. */
static void cr_P_scale(int32_t *word, int32_t *frac, int32_t s, int32_t lo, int32_t hi,
                       uint32_t *n)
{
    const int64_t w = *word, f = *frac;
    int64_t nw, v;
    uint32_t nl;
    if (s == 0) {
        return;
    }
    if (s > 0) {
        if (s <= 31) {
            /* V 2^s + 2^31 = (w 2^s + (t >> 32)) 2^32 + (t mod 2^32), t = f 2^s + 2^31 */
            const int64_t t = cr_lsl64(f, s) + ((int64_t)1 << 31);
            nw = cr_lsl64(w, s) + (t >> 32);
            nl = (uint32_t)t;
        } else if (w != 0) {
            /* |V 2^s| >= 2^31 2^32: outside every word */
            nw = w > 0 ? I62 : -I62;
            nl = 0u;
        } else {
            /* V = f: the word f 2^(s-32) exactly, no fraction */
            nw = s - 32 <= 31 ? cr_lsl64(f, s - 32) : (f > 0 ? I62 : f < 0 ? -I62 : 0);
            nl = 0x80000000u;
        }
    } else {
        /* rsh(V, r) = ((V >> a) + 1) >> 1, a = r - 1, with V >> a from the word and the
         * fraction: V = w 2^32 + f, so V >> a = w 2^(32-a) + (f >> a) for a < 32 and
         * (w - (f < 0)) >> (a - 32) for a >= 32 */
        const int32_t a = -s - 1;
        if (a == 0) {
            v = w * ((int64_t)1 << 31) + ((f + 1) >> 1);
        } else if (a <= 31) {
            v = ((cr_lsl64(w, 32 - a) + cr_asr64(f, a)) + 1) >> 1;
        } else {
            v = (cr_asr64(w - (f < 0 ? 1 : 0), a - 32 < 63 ? a - 32 : 63) + 1) >> 1;
        }
        /* the word rounded half up, the fraction + 2^31 its low word */
        nw = (v + ((int64_t)1 << 31)) >> 32;
        nl = (uint32_t)((uint64_t)v + 0x80000000u);
    }
    if (nw > hi) {
        *n += 1u;
        nw = hi;
        nl = 0xFFFFFFFFu;
    } else if (nw < lo) {
        *n += 1u;
        nw = lo;
        nl = 0u;
    }
    *word = (int32_t)nw;
    *frac = (int32_t)(nl ^ 0x80000000u);
}

/* floor(m 2^e), or ceil(m 2^e) where ``up``, saturated at 2^62 */
static int64_t cr_scaled(uint64_t m, int32_t e, int up)
{
    if (e >= 0) {
        return (e >= 62 || m >= (uint64_t)cr_asr64(I62, e)) ? I62 : cr_lsl64((int64_t)m, e);
    }
    if (-e >= 64) {
        return up && m != 0u ? 1 : 0;
    }
    return (int64_t)cr_lsr64(m + (up ? (uint64_t)cr_lsl64(1, -e) - 1u : 0u), -e);
}

/* the growth d of a column (or of the output: ``c``, its word's shift sh and fraction bits
 * f) at this sample: 2^(f + d) >= 16 |(X + O) m| 2^-sh for the first value of a pending
 * one (*first set), 4 |...| for a value beyond 2^f (``over``), else 0 */
static int32_t cr_growth(const canrls_target *S, const canrls_column *c, int pending,
                         int over, int32_t sh, int32_t f, uint8_t *first)
{
    const int64_t x = cr_state(S, c);
    const uint64_t big = (uint64_t)(x < 0 ? -x : x);
    *first = (uint8_t)(pending && big != 0u);
    if (pending ? big == 0u : !over) {
        return 0;
    }
    return cr_clog2_mul(big, (uint32_t)(c->m < 0 ? -c->m : c->m)) - sh - f + (pending ? 4 : 2);
}

/* the exponents change before this sample (spec TargetEstimator._adapt) */
void canrls_target_adapt(canrls_target *S, uint32_t i, const int64_t *phi, int64_t y)
{
    const canrls_equation *e = &S->model->equations[i];
    canrls_target_eq *q = &S->eq[i];
    const uint32_t n = e->n;
    int32_t d[CANRLS_N_MAX + 1];    /* the columns', then the output's growth */
    uint8_t first[CANRLS_N_MAX + 1];
    int32_t theta[CANRLS_N_MAX];
    uint32_t frac[CANRLS_N_MAX];
    int32_t P[CANRLS_TRI(CANRLS_N_MAX)];
    int32_t Pf[CANRLS_TRI(CANRLS_N_MAX)];
    int32_t dy, dmax = 0, s = 0, ex, e_new;
    uint32_t j, k, idx;
    if (n == 0u) {
        return; /* an equation has columns: every array below then has its first word */
    }
    for (j = 0; j <= n; j++) {
        /* a column: 16 |phi| <= 2^(f + d) at its first value, 4 |phi| <= 2^(f + d) beyond
         * 2^f where adaptive; the output likewise */
        const int col = j < n;
        const canrls_column *c = col ? &e->columns[j] : &e->output;
        const int32_t f = col ? e->f_phi : e->f_y;
        const int64_t v = col ? phi[j] : y;
        const int over = (!col || c->adaptive)
                         && (uint64_t)(v < 0 ? -v : v) > (uint64_t)cr_lsl64(1, f);
        d[j] = cr_growth(S, c, col ? q->pending[j] : q->pending_y, over,
                         col ? q->sh[j] : q->sh_y, f, &first[j]);
    }
    dy = d[n];
    /* theta_j takes 2^(d_j - d_y): the output moves where an estimate would leave half its
     * bound, |theta_j| 2^(d_j - dy) <= 2^h 2^s */
    for (j = 0; j < n; j++) {
        const int32_t w = canrls_theta_q31(&q->rls, j);
        if (w != 0) {
            const int32_t sj = cr_clog2((uint64_t)(w < 0 ? -(int64_t)w : w)) + d[j] - dy - e->theta_h;
            s = sj > s ? sj : s;
        }
    }
    dy += s;
    /* the kernel's state in the new units: theta_j 2^(d_j - d_y) in its 64 bits; P_jk
     * 2^(d_j + d_k) with the block exponent lowered by twice the largest growth */
    cr_read(q, n, theta, frac, P, Pf);
    {
        const int64_t lo = cr_shl(e->plan->theta_lo, 32);
        const int64_t hi = cr_shl(e->plan->theta_hi, 32) + 0xFFFFFFFF;
        for (j = 0; j < n; j++) {
            int64_t v = cr_shl(theta[j], 32) + (int64_t)frac[j];
            const int32_t sj = d[j] - dy;
            if (sj >= 0) {
                /* v 2^s, saturated */
                if (v != 0 && (sj >= 63 || v > cr_asr64(hi, sj) || v < cr_asr64(lo, sj))) {
                    q->rls.counts[CANRLS_S_THETA]++;
                    v = v > 0 ? hi : lo;
                } else if (v != 0) {
                    v = cr_lsl64(v, sj);
                }
            } else {
                v = cr_rsh64(v, -sj);
            }
            theta[j] = (int32_t)(v >> 32);
            frac[j] = (uint32_t)(v & 0xFFFFFFFF);
        }
    }
    for (j = 0; j < n; j++) {
        if (!first[j]) {
            dmax = d[j] > dmax ? d[j] : dmax;
        }
    }
    ex = q->rls.e;
    e_new = ex - 2 * dmax;
    e_new = e_new < 0 ? 0 : e_new;
    idx = 0;
    for (j = 0; j < n; j++) {
        for (k = j; k < n; k++, idx++) {
            /* P_jj / 4 for a first value (the prior alpha 2^-8 for alpha 2^-10), else
             * P_jk 2^(d_j + d_k), at e_new, in 64 bits */
            const int32_t sjk = (j == k && first[j]) ? e_new - ex - 2 : d[j] + d[k] + e_new - ex;
            cr_P_scale(&P[idx], &Pf[idx], sjk, e->plan->P_lo, e->plan->P_hi,
                       &q->rls.counts[CANRLS_S_P]);
        }
    }
    cr_restore(q, e, theta, frac, P, Pf, e_new, 0);
    /* a column that grew takes the weakest prior of the start: delta = alpha_f -
     * alpha_j 2^(-2 d_j), as one update with the regressor sqrt(delta) e_j and y = 0 */
    for (j = 0; j < n; j++) {
        if (d[j] != 0 && !q->pending[j]) {
            const canrls_dyadic r = {q->ridge[j].m, q->ridge[j].e - 2 * d[j]};
            /* D = floor(alpha_f 2^(2 f)) - ceil(alpha_j 2^(2 f)) */
            const int64_t D = cr_scaled(e->floor_ridge.m, e->floor_ridge.e + 2 * e->f_phi, 0)
                              - cr_scaled(r.m, r.e + 2 * e->f_phi, 1);
            if (D > 0) {
                int64_t qv = cr_isqrt(D);
                qv = qv < e->plan->phi_hi ? qv : e->plan->phi_hi;
                if (qv != 0) {
                    int32_t ph[CANRLS_N_MAX];
                    memset(ph, 0, sizeof ph);
                    ph[j] = (int32_t)qv;
                    (void)canrls_update_q31(&q->rls, ph, 0, NULL);
                }
                q->ridge[j] = e->floor_ridge;
                q->terms[j] = e->floor_term;
            } else {
                q->ridge[j] = r;
                /* terms_j 2^(2 d_j), saturated at 2^62 */
                if (q->terms[j] != 0
                    && (d[j] >= 31 || q->terms[j] > cr_asr64(I62, 2 * d[j]))) {
                    q->terms[j] = I62;
                } else if (q->terms[j] != 0) {
                    q->terms[j] = cr_lsl64(q->terms[j], 2 * d[j]);
                }
            }
        } else if (d[j] != 0) {
            /* the ridge scales with the column (then set below) */
            q->ridge[j].e -= 2 * d[j];
        }
    }
    for (j = 0; j < n; j++) {
        if (first[j]) {
            /* the first value: the prior alpha 2^-8 (its P_jj set above) */
            q->pending[j] = 0u;
            q->ridge[j] = e->first_ridge;
            q->terms[j] = e->first_term;
        }
    }
    if (first[n]) {
        q->pending_y = 0u;
    }
    for (j = 0; j < n; j++) {
        q->sh[j] += d[j];
        q->exponents[j] += d[j];
    }
    q->sh_y += dy;
    q->exponents[n] += dy;
    q->rescales++;
    if (e->trace_follows) {
        cr_read(q, n, theta, frac, P, Pf);
        cr_restore(q, e, theta, frac, P, Pf, q->rls.e, 1);
    }
}

/* ------------------------------------------------------------------ shared steps */

void canrls_target_step(canrls_target *S, uint32_t i, const int64_t *phi, int64_t y)
{
    const canrls_equation *e = &S->model->equations[i];
    int32_t phq[CANRLS_N_MAX];
    uint32_t j;
    for (j = 0; j < e->n; j++) {
        phq[j] = cr_sat32(phi[j]);
    }
    cr_step(&S->eq[i], phq, cr_sat32(y), e->rms_shift);
}

uint32_t canrls_target_sampled(canrls_target *S)
{
    return cr_sampled(S, S->model->publish_every);
}

uint32_t canrls_target_reject(canrls_target *S, uint32_t reason)
{
    S->rejects[reason]++;
    S->frame_loss = 1u;
    return 0u;
}

int canrls_target_pair(canrls_target *S, uint32_t mi, int32_t counter, uint32_t t)
{
    const canrls_target_model *M = S->model;
    return cr_pair(S, 1u << mi, M->match_counters ? counter : -1, M->tol_ticks, t);
}

#ifndef CANRLS_FRONT
/* ------------------------------------------------------------------ the table-driven path */

/* the columns and the output of a used sample: rsh((X + O) m, sh) */
static void cr_values(const canrls_target *S, const canrls_equation *e,
                      const canrls_target_eq *q, int64_t *phi, int64_t *y)
{
    uint32_t j;
    for (j = 0; j < e->n; j++) {
        phi[j] = cr_mul_rsh(cr_state(S, &e->columns[j]), e->columns[j].m, q->sh[j]);
    }
    *y = cr_mul_rsh(cr_state(S, &e->output), e->output.m, q->sh_y);
}

/* whether this used sample changes the normalisation */
static int cr_changes(const canrls_target *S, const canrls_equation *e,
                      const canrls_target_eq *q, const int64_t *phi, int64_t y)
{
    const int64_t lim = (int64_t)1 << e->f_phi;
    const int64_t lim_y = (int64_t)1 << e->f_y;
    uint32_t j;
    for (j = 0; j < e->n; j++) {
        if (q->pending[j]) {
            if (cr_state(S, &e->columns[j]) != 0) {
                return 1;
            }
        } else if (e->columns[j].adaptive && (phi[j] > lim || -phi[j] > lim)) {
            return 1;
        }
    }
    if (q->pending_y) {
        return cr_state(S, &e->output) != 0;
    }
    return y > lim_y || -y > lim_y;
}

static void cr_update(canrls_target *S, uint32_t i)
{
    const canrls_equation *e = &S->model->equations[i];
    canrls_target_eq *q = &S->eq[i];
    int64_t phi[CANRLS_N_MAX], y;
    cr_values(S, e, q, phi, &y);
    if (cr_changes(S, e, q, phi, y)) {
        canrls_target_adapt(S, i, phi, y);
        cr_values(S, e, q, phi, &y);
    }
    canrls_target_step(S, i, phi, y);
}

/* one sample, complete in S->raw, at time t */
static uint32_t cr_sample(canrls_target *S, uint32_t t)
{
    const canrls_target_model *M = S->model;
    int32_t u[CANRLS_TARGET_FILTER_MAX];
    const int32_t dt = (int32_t)(t - S->last_t);
    int64_t w;
    uint32_t i;
    if (!S->has_t || dt < 0 || dt > M->gap_ticks) {
        /* the first sample, time going back, or a period missing: restart */
        if (S->has_t) {
            S->rejects[CANRLS_R_RESTARTS]++;
        }
        canrls_target_restart(S);
    }
    S->has_t = 1u;
    S->last_t = t;
    cr_inputs(S, u);
    cr_filter(S, u);
    /* the speed of the selection: W = raw 2^16 + offset */
    w = (int64_t)S->raw[CANRLS_SPEED] * ((int64_t)1 << W_FRAC) + M->w_offset;
    for (i = 0; i < M->neq; i++) {
        const canrls_equation *e = &M->equations[i];
        canrls_target_eq *q = &S->eq[i];
        const int64_t aw = w < 0 ? -w : w;
        const int out = aw < e->min_w || (e->max_w >= 0 && aw > e->max_w)
                        || (e->cross && ((q->w_last < 0 && w > 0) || (w < 0 && q->w_last > 0)));
        if (out) {
            q->left = e->warmup + 1;
        }
        q->w_last = w;
        if (q->left > 0) {
            q->left--;
            continue;
        }
        cr_update(S, i);
    }
    return canrls_target_sampled(S);
}

uint32_t canrls_target_frame(canrls_target *S, uint32_t id, uint32_t extended,
                             const uint8_t *data, uint32_t len, uint32_t t)
{
    const canrls_target_model *M = S->model;
    const canrls_message *msg = NULL;
    int32_t raws[CANRLS_TARGET_ROLES];
    uint32_t mi, k;
    int32_t counter = -1;
    uint64_t le = 0u, be = 0u;
    for (mi = 0; mi < M->nmsg; mi++) {
        if (M->messages[mi].id == id && M->messages[mi].extended == (extended != 0u)) {
            msg = &M->messages[mi];
            break;
        }
    }
    if (msg == NULL) {
        return 0u;
    }
    /* length: the DBC's */
    if (len != msg->dlc) {
        return canrls_target_reject(S, CANRLS_R_LENGTH);
    }
    /* E2E CRC-8: over the ID (2 bytes, little endian), then bytes 1..dlc-1 */
    if (msg->crc) {
        uint32_t c = 0xFFu;
        c = cr_crc8[c ^ (id & 0xFFu)];
        c = cr_crc8[c ^ ((id >> 8) & 0xFFu)];
        for (k = 1; k < len; k++) {
            c = cr_crc8[c ^ data[k]];
        }
        if ((c ^ 0xFFu) != data[0]) {
            return canrls_target_reject(S, CANRLS_R_CRC);
        }
    }
    /* the payload as one word, little and big endian (bytes after its end are 0) */
    {
        uint8_t b[8] = {0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u};
        uint32_t w0, w1;
        for (k = 0; k < len; k++) {
            b[k] = data[k];
        }
        w0 = (uint32_t)b[0] | (uint32_t)b[1] << 8 | (uint32_t)b[2] << 16 | (uint32_t)b[3] << 24;
        w1 = (uint32_t)b[4] | (uint32_t)b[5] << 8 | (uint32_t)b[6] << 16 | (uint32_t)b[7] << 24;
        le = (uint64_t)w1 << 32 | w0;
        be = (uint64_t)cr_bswap32(w0) << 32 | cr_bswap32(w1);
    }
    /* alive counter: one equal to the last accepted is a repeat */
    if (msg->has_counter) {
        counter = cr_extract(&msg->counter, le, be);
        if (counter == S->last_counter[mi]) {
            return canrls_target_reject(S, CANRLS_R_REPEATED);
        }
        S->last_counter[mi] = counter;
    }
    /* strict range of every mapped field */
    for (k = 0; k < msg->nroles; k++) {
        const canrls_field *f = &M->roles[msg->roles[k]];
        int32_t v = 0;
        const int ok = f->is_float ? cr_float(f, le, be, &v) : (v = cr_extract(f, le, be), 1);
        if (!ok || v < f->lo || v > f->hi) {
            return canrls_target_reject(S, CANRLS_R_RANGE);
        }
        raws[k] = v;
    }
    /* pair: the frames of one period */
    if (!canrls_target_pair(S, mi, counter, t)) {
        return 0u;
    }
    for (k = 0; k < msg->nroles; k++) {
        S->raw[msg->roles[k]] = raws[k];
    }
    if (S->open_mask != (1u << M->nmsg) - 1u) {
        return 0u;
    }
    S->open_mask = 0u;
    return cr_sample(S, t);
}
#endif /* CANRLS_FRONT */


/* ------------------------------------------------------------------ frames out */

/* frame f of the signals v[0..k) into out[*nf] (while *nf < max): each signal's value mod
 * 2^length at its start bit of the 64-bit payload (its words lo and hi), the payload's 8
 * bytes little endian */
static void cr_emit(canrls_can_frame *out, uint32_t *nf, uint32_t max,
                    const canrls_out_frame *f, const uint32_t *v, uint32_t k)
{
    uint32_t lo = 0u, hi = 0u, j;
    if (*nf >= max) {
        return;
    }
    for (j = 0; j < k; j++) {
        /* (a value is a word: a length of 32 or more keeps it whole) */
        const uint32_t len = f->length[j], s = f->start[j];
        const uint32_t x = len >= 32u ? v[j] : v[j] & ((1u << len) - 1u);
        if (s >= 32u) {
            hi |= x << (s - 32u);
        } else if (s > 0u) {
            lo |= x << s;
            hi |= x >> (32u - s);
        } else {
            lo |= x;
        }
    }
    out += (*nf)++;
    out->id = f->id;
    out->dlc = 8u;
    for (j = 0; j < 4u; j++) {
        out->data[j] = (uint8_t)(lo >> (8u * j));
        out->data[j + 4u] = (uint8_t)(hi >> (8u * j));
    }
}

void canrls_target_theta(const canrls_target *S, uint32_t i, int32_t *word, int32_t *exp)
{
    const canrls_target_model *M = S->model;
    uint32_t k;
    for (k = 0; k < M->neq; k++) {
        const canrls_equation *e = &M->equations[k];
        if (i < e->n) {
            const canrls_target_eq *q = &S->eq[k];
            *word = canrls_theta_q31(&q->rls, i);
            *exp = q->exponents[e->n] - q->exponents[i] - e->f_theta;
            return;
        }
        i -= e->n;
    }
    *word = 0;
    *exp = 0;
}

uint32_t canrls_target_publish(canrls_target *S, canrls_can_frame *out, uint32_t max)
{
    const canrls_target_model *M = S->model;
    const uint32_t cnt = S->publications & 0xFu;
    uint32_t nf = 0u, idx = 0u, i, j, flags = 0u;
    uint32_t v[8];
    if (!M->has_frames) {
        return 0u;
    }
    for (i = 0; i < M->neq; i++) {
        const canrls_equation *e = &M->equations[i];
        const canrls_target_eq *q = &S->eq[i];
        for (j = 0; j < e->n; j++, idx++) {
            const uint32_t valid = q->updates > 0u;
            /* FixedValue = theta_j 2^(s_y - s_j - f_theta), float32 from the integers */
            v[0] = idx;
            v[1] = cnt;
            v[2] = valid;
            v[3] = valid ? cr_f32_bits(canrls_theta_q31(&q->rls, j),
                                       q->exponents[e->n] - q->exponents[j] - e->f_theta)
                         : 0u;
            cr_emit(out, &nf, max, &M->estimate, v, 4u);
        }
    }
    if (S->publications % 10u == 0u) {
        for (i = 0; i < M->nparams; i++) {
            v[0] = i;
            v[1] = idx;
            v[2] = M->param_info[i][0];
            v[3] = M->param_info[i][1];
            v[4] = M->param_order[i];
            v[5] = M->param_info[i][2];
            cr_emit(out, &nf, max, &M->info, v, 6u);
        }
    }
    {
        const canrls_equation *e = &M->equations[0];
        const canrls_target_eq *q = &S->eq[0];
        /* ResidualRms = sqrt(ms) 2^(s_y - f_eps) */
        v[0] = cr_f32_bits(cr_isqrt(q->ms), q->exponents[e->n] - e->f_eps);
        v[1] = q->updates;
        cr_emit(out, &nf, max, &M->status, v, 2u);
    }
    for (i = 0; i < M->neq; i++) {
        flags |= S->eq[i].flags;
        S->eq[i].flags = 0u;
    }
    for (j = 0; j < 5u; j++) {
        /* the flags' bits 0, 1, 2 and 3 at 0, 1, 2 and 4; frame loss at 3 */
        v[j] = (flags >> (j - (j > 3u))) & 1u;
    }
    v[3] = S->frame_loss;
    v[5] = cnt;
    v[6] = M->active_effects;
    v[7] = 0u;
    cr_emit(out, &nf, max, &M->health, v, 8u);
    S->frame_loss = 0u;
    S->publications++;
    return nf;
}
