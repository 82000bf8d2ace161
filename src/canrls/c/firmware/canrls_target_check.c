/*
 * canrls_target_check.c -- the validity check of a restored state (canrls_target_check.h).
 *
 * SPDX-License-Identifier: MIT
 *
 * Each check states the invariant canrls_target.c and canrls_fixed.c keep for the field
 * (docs/target.md, "Restore"). Integers only, no libc beyond <string.h>.
 */
#include "canrls_target_check.h"

#include <string.h>

#include "canrls_target_math.h"

/* the plan is compared as bytes: no padding in it (46 words of 32 bits, 2 of 64) */
typedef char canrls_plan_has_no_padding[sizeof(canrls_plan_q31) == 46 * 4 + 2 * 8 ? 1 : -1];

#define CK_I62 ((int64_t)1 << 62)
#define CK_X_MAX ((int64_t)1 << 60) /* |x1|, |x2| < 2^60: cr_svf_row's bound */

static int ck_zero(const void *p, size_t n)
{
    const unsigned char *b = (const unsigned char *)p;
    size_t i;
    for (i = 0; i < n; i++) {
        if (b[i] != 0u) {
            return 0;
        }
    }
    return 1;
}

/* the values cr_extract() gives for an integer field (lo..hi, int64) */
static void ck_field_range(const canrls_field *f, int64_t *lo, int64_t *hi)
{
    if (f->length == 0u || f->length >= 32u || f->biased) {
        *lo = INT32_MIN;
        *hi = INT32_MAX;
    } else if (f->is_signed) {
        *lo = -((int64_t)1 << (f->length - 1u));
        *hi = ((int64_t)1 << (f->length - 1u)) - 1;
    } else {
        *lo = 0;
        *hi = ((int64_t)1 << f->length) - 1;
    }
}

/* an alive counter of message mi (-1: none yet) */
static int ck_counter(const canrls_target_model *M, uint32_t mi, int32_t v)
{
    int64_t lo, hi;
    if (v == -1) {
        return 1;
    }
    if (!M->messages[mi].has_counter) {
        return 0;
    }
    ck_field_range(&M->messages[mi].counter, &lo, &hi);
    return v >= lo && v <= hi;
}

/* the kernel of equation e: its words in range, trw and the derived fields as
 * canrls_init_q31() and canrls_restore_q31() make them for these words */
static int ck_kernel(const canrls_target_eq *q, const canrls_equation *e)
{
    const canrls_rls_q31 *R = &q->rls;
    const canrls_plan_q31 *p = &q->plan;
    const uint32_t n = e->n, m = CANRLS_TRI(e->n);
    int32_t theta[CANRLS_N_MAX], Pw[CANRLS_TRI(CANRLS_N_MAX)], Pf[CANRLS_TRI(CANRLS_N_MAX)];
    uint32_t frac[CANRLS_N_MAX], j;
    canrls_rls_q31 T;
    /* 1/2 < c <= 1 in the lam format (c / 2 as soon as c > 1, or c folded into P) */
    if (R->plan != p || R->n != n || R->frozen > 1u || R->e < 0 || R->e > p->e_max
        || R->c > p->one_lam || (int64_t)R->c * 2 <= p->one_lam) {
        return 0;
    }
    if (!ck_zero(&R->theta_q[n], sizeof R->theta_q[0] * (CANRLS_N_MAX - n))
        || !ck_zero(&R->P[m], sizeof R->P[0] * (CANRLS_TRI(CANRLS_N_MAX) - m))
        || !ck_zero(&R->K[n], sizeof R->K[0] * (CANRLS_N_MAX - n))) {
        return 0;
    }
    for (j = 0; j < n; j++) {
        theta[j] = canrls_theta_q31(R, j);
        frac[j] = canrls_theta_frac_q31(R, j);
    }
    for (j = 0; j < m; j++) {
        Pw[j] = canrls_P_q31(R, j);
        Pf[j] = canrls_P_frac_q31(R, j);
    }
    /* the words within theta_lo..theta_hi and P_lo..P_hi: canrls_restore_q31 checks them */
    if (canrls_init_q31(&T, p, n, e->p0, e->e0) != CANRLS_OK
        || canrls_restore_q31(&T, theta, frac, Pw, Pf, R->e, R->c) != CANRLS_OK) {
        return 0;
    }
    return T.trw == R->trw && T.wu_lo == R->wu_lo && T.wu_hi == R->wu_hi && T.wide == R->wide;
}

/* the shifts a column (or the output, f its fraction bits) can take, *lo..*hi: it starts
 * at c->sh; a pending one's first value sets it to clog2(|X + O| |m|) - f + 4 >=
 * clog2(|m|) - f + 4; growth raises it, to at most clog2(2^61 2^31) - f + 4 */
static void ck_shift_range(const canrls_column *c, int32_t f, int32_t *lo, int32_t *hi)
{
    const uint32_t am = (uint32_t)(c->m < 0 ? -(int64_t)c->m : c->m);
    const int32_t top = 92 - f + 4;
    int32_t first = 0; /* clog2(|m|) = the bit length of |m| - 1 */
    while (first < 32 && ((am - 1u) >> first) != 0u) {
        first++;
    }
    first += 4 - f;
    *lo = c->pending && first < c->sh ? first : c->sh;
    *hi = top > c->sh ? top : c->sh;
}

/* a shift sh and its exponent ex: the exponent moves with the shift; a column neither
 * pending nor adaptive (fixed), or still pending, keeps its start; else within the range
 * (up: how far beyond it the output's can go) */
static int ck_shift(const canrls_column *c, int32_t f, int32_t sh, int32_t ex, int fixed,
                    int32_t up)
{
    int32_t lo, hi;
    ck_shift_range(c, f, &lo, &hi);
    if ((int64_t)ex - sh != (int64_t)c->exponent - c->sh) {
        return 0;
    }
    if (fixed) {
        return sh == c->sh;
    }
    return sh >= lo && (int64_t)sh <= (int64_t)hi + up;
}

/* a column's ridge and trace term: the start's, the floor's or a first value's prior, the
 * ridge's exponent lowered by twice the column's growth since (at most twice its shift
 * range), the term raised as much (saturated at 2^62); the start's while pending */
static int ck_prior(const canrls_equation *e, const canrls_target_eq *q, uint32_t j,
                    int32_t f)
{
    const canrls_dyadic r = q->ridge[j];
    const canrls_dyadic *from[3];
    int32_t lo, hi;
    uint32_t k;
    from[0] = &e->ridge[j];
    from[1] = &e->floor_ridge;
    from[2] = &e->first_ridge;
    ck_shift_range(&e->columns[j], f, &lo, &hi);
    if (q->terms[j] < 0 || q->terms[j] > CK_I62) {
        return 0;
    }
    if (q->pending[j]) {
        return r.m == e->ridge[j].m && r.e == e->ridge[j].e && q->terms[j] == e->trace_terms[j];
    }
    for (k = 0; k < 3u; k++) {
        const int64_t d = (int64_t)from[k]->e - r.e;
        if (r.m == from[k]->m && d >= 0 && d <= 2 * ((int64_t)hi - lo)) {
            return 1;
        }
    }
    return 0;
}

/* equation i's state */
static int ck_equation(const canrls_target *S, uint32_t i)
{
    const canrls_target_model *M = S->model;
    const canrls_equation *e = &M->equations[i];
    const canrls_target_eq *q = &S->eq[i];
    const uint32_t n = e->n;
    const canrls_field *speed = &M->roles[CANRLS_SPEED];
    const int64_t rlo = speed->length ? speed->lo : 0, rhi = speed->length ? speed->hi : 0;
    const int64_t eps_max = -(int64_t)q->plan.eps_lo > q->plan.eps_hi ? -(int64_t)q->plan.eps_lo
                                                                      : q->plan.eps_hi;
    canrls_plan_q31 plan;
    uint32_t j;
    if (n > CANRLS_N_MAX) {
        return CANRLS_SF_PLAN;
    }
    for (j = 0; j < n; j++) {
        if (q->pending[j] > 1u || (q->pending[j] && !e->columns[j].pending)) {
            return CANRLS_SF_FLAGS;
        }
    }
    if (q->pending_y > 1u || (q->pending_y && !e->output.pending)) {
        return CANRLS_SF_FLAGS;
    }
    /* the output's shift: moved also by the estimates (theta_j 2^(d_j - d_y) within half
     * its bound), at most 32 - theta_h beyond the growth in each rescale, and a rescale
     * needs a growth of a column or the output: at most `range` of them */
    {
        int64_t range, up;
        int32_t lo, hi;
        ck_shift_range(&e->output, e->f_y, &lo, &hi);
        range = (int64_t)hi - lo;
        for (j = 0; j < n; j++) {
            const canrls_column *c = &e->columns[j];
            ck_shift_range(c, e->f_phi, &lo, &hi);
            if (!ck_shift(c, e->f_phi, q->sh[j], q->exponents[j],
                          q->pending[j] || (!c->pending && !c->adaptive), 0)) {
                return CANRLS_SF_SHIFT;
            }
            range += (int64_t)hi - lo;
        }
        up = range * (32 + (e->theta_h < 0 ? -(int64_t)e->theta_h : 0) + 1);
        if (!ck_shift(&e->output, e->f_y, q->sh_y, q->exponents[n], q->pending_y,
                      (int32_t)(up < (1 << 24) ? up : (1 << 24)))) {
            return CANRLS_SF_SHIFT;
        }
    }
    for (j = 0; j < n; j++) {
        if (!ck_prior(e, q, j, e->f_phi)) {
            return CANRLS_SF_PRIOR;
        }
    }
    if (!ck_zero(&q->sh[n], sizeof q->sh[0] * (CANRLS_N_MAX - n))
        || !ck_zero(&q->exponents[n + 1u], sizeof q->exponents[0] * (CANRLS_N_MAX - n))
        || !ck_zero(&q->pending[n], sizeof q->pending[0] * (CANRLS_N_MAX - n))
        || !ck_zero(&q->ridge[n], sizeof q->ridge[0] * (CANRLS_N_MAX - n))
        || !ck_zero(&q->terms[n], sizeof q->terms[0] * (CANRLS_N_MAX - n))) {
        return CANRLS_SF_UNUSED;
    }
    /* the plan copy: the model's, its trace bound the one the terms give */
    memcpy(&plan, e->plan, sizeof plan);
    plan.trace_max_lam = canrls_target_trace_bound(e, q);
    if (memcmp(&plan, &q->plan, sizeof plan) != 0) {
        return CANRLS_SF_PLAN;
    }
    if (!ck_kernel(q, e)) {
        return CANRLS_SF_KERNEL;
    }
    /* left: warmup after a restart or a speed out of limits, counted down; w_last: 0 or
     * W = raw 2^16 + w_offset of a speed in its range */
    if (q->left < 0 || q->left > e->warmup
        || (q->w_last != 0 && (q->w_last < rlo * 65536 + M->w_offset
                               || q->w_last > rhi * 65536 + M->w_offset))) {
        return CANRLS_SF_WARMUP;
    }
    /* ms <- ms + (eps^2 - ms) >> rms_shift stays within 0..max eps^2 */
    if ((q->flags & ~(uint32_t)(CANRLS_FLAG_WINDUP | CANRLS_FLAG_LOW_EXCITATION
                               | CANRLS_FLAG_SATURATION | CANRLS_FLAG_FROZEN)) != 0u
        || q->ms < 0 || q->ms > eps_max * eps_max) {
        return CANRLS_SF_RESIDUAL;
    }
    return CANRLS_OK;
}

/* filter i's state: a constant's is fixed; else |x| < 2^60 (a narrow filter's int32) and
 * the last input split as cr_split_input() splits one */
static int ck_filter(const canrls_target *S, uint32_t i)
{
    const canrls_filter *f = &S->model->filters[i];
    const int32_t fx = f->fx;
    if (f->kind == CANRLS_SRC_CONST) {
        return S->x1[i] == ((int64_t)1 << 30) * ((int64_t)1 << fx) && S->x2[i] == 0
               && S->primed[i] == 1u && S->uph[i] == 0 && S->upl[i] == 0;
    }
    if (S->primed[i] > 1u || S->x1[i] <= -CK_X_MAX || S->x1[i] >= CK_X_MAX
        || S->x2[i] <= -CK_X_MAX || S->x2[i] >= CK_X_MAX || fx < 0 || fx > 40) {
        return 0;
    }
    if (cr_narrow(f) && (S->x1[i] != (int32_t)S->x1[i] || S->x2[i] != (int32_t)S->x2[i])) {
        return 0; /* a narrow filter's states are int32 */
    }
    if (fx >= 31) {
        return S->upl[i] == 0 && S->uph[i] % ((int32_t)1 << (fx - 31)) == 0;
    }
    return S->uph[i] >= -((int32_t)1 << fx) && S->uph[i] <= ((int32_t)1 << fx) - 1
           && S->upl[i] >= 0 && (S->upl[i] & (((int32_t)1 << fx) - 1)) == 0;
}

int canrls_target_check_state(const canrls_target *S, const canrls_target_model *M)
{
    uint32_t i;
    int r;
    if (S == NULL || M == NULL || S->model != M || M->nmsg < 1u
        || M->nmsg > CANRLS_TARGET_MSG_MAX || M->nfilters > CANRLS_TARGET_FILTER_MAX
        || M->neq < 1u || M->neq > CANRLS_TARGET_EQ_MAX) {
        return CANRLS_SF_MODEL;
    }
    for (i = 0; i < CANRLS_TARGET_MSG_MAX; i++) {
        if (i < M->nmsg ? !ck_counter(M, i, S->last_counter[i]) : S->last_counter[i] != 0) {
            return i < M->nmsg ? CANRLS_SF_LAST_COUNTER : CANRLS_SF_UNUSED;
        }
    }
    /* the period being paired: some messages, never all (a complete one is a sample);
     * its key -1 or an alive counter */
    {
        const uint32_t all = (1u << M->nmsg) - 1u;
        int key = S->open_counter == -1;
        for (i = 0; i < M->nmsg && !key; i++) {
            key = M->match_counters && ck_counter(M, i, S->open_counter);
        }
        if ((S->open_mask & ~all) != 0u || S->open_mask == all || !key) {
            return CANRLS_SF_OPEN;
        }
    }
    for (i = 0; i < CANRLS_TARGET_ROLES; i++) {
        const canrls_field *f = &M->roles[i];
        if (S->raw[i] != 0 && (f->length == 0u || S->raw[i] < f->lo || S->raw[i] > f->hi)) {
            return CANRLS_SF_RAW;
        }
    }
    if (S->has_t > 1u || S->frame_loss > 1u) {
        return CANRLS_SF_FLAGS;
    }
    if (S->since_publish >= M->publish_every) {
        return CANRLS_SF_PUBLISH;
    }
    for (i = 0; i < CANRLS_TARGET_FILTER_MAX; i++) {
        if (i >= M->nfilters) {
            if (S->x1[i] != 0 || S->x2[i] != 0 || S->uph[i] != 0 || S->upl[i] != 0
                || S->primed[i] != 0u) {
                return CANRLS_SF_UNUSED;
            }
        } else if (!ck_filter(S, i)) {
            return CANRLS_SF_FILTER;
        }
    }
    for (i = 0; i < CANRLS_TARGET_EQ_MAX; i++) {
        if (i >= M->neq) {
            if (!ck_zero(&S->eq[i], sizeof S->eq[i])) {
                return CANRLS_SF_UNUSED;
            }
            continue;
        }
        r = ck_equation(S, i);
        if (r != CANRLS_OK) {
            return r;
        }
    }
    return CANRLS_OK;
}

const char *canrls_target_state_field(int field)
{
    static const char *const names[] = {
        "model", "last_counter", "open_mask/open_counter", "raw", "a flag (0 or 1)",
        "since_publish", "a filter's state (x1, x2, uph, upl)", "an equation's plan",
        "an equation's kernel (rls)", "a shift or exponent (sh, sh_y, exponents)",
        "a ridge or trace term (ridge, terms)", "left or w_last", "ms or flags",
        "the state beyond the model's equations, filters or messages"};
    return field >= CANRLS_SF_MODEL && field <= CANRLS_SF_UNUSED ? names[field - 1] : "?";
}
