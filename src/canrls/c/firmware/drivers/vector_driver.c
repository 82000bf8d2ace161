/*
 * vector_driver.c -- runs the C kernel over test vectors written by tools/gen_ckernel.py.
 *
 * SPDX-License-Identifier: MIT
 *
 * usage: vector_driver IN OUT
 *
 * IN (whitespace-separated text):
 *     plan <count>            then <count> lines "name value" (Python FixedRLS.constants)
 *     n <n>
 *     state theta[n] theta_frac[n] P_up[n(n+1)/2] P_frac_up[n(n+1)/2] e c frozen
 *           counts[NSITES]
 *     steps <N>               then N rows "frozen phi[n] y"
 * OUT: one line per step (the layout of tools/gen_ckernel.py expected_lines):
 *     applied eps trace e flags theta[n] theta_frac[n] P_up[..] P_frac_up[..] c
 *     counts[NSITES]
 * Exit status 0, or 2 with a message on stderr for a malformed IN (unknown constant,
 * missing constant, a value the kernel's init/restore refuses).
 */
#include <stddef.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "canrls_fixed.h"

#define FIELD(name, type) { #name, offsetof(canrls_plan_q31, name), sizeof(type) }

static const struct {
    const char *name;
    size_t offset;
    size_t size;
} fields[] = {
    FIELD(phi_lo, int32_t), FIELD(phi_hi, int32_t), FIELD(y_lo, int32_t),
    FIELD(y_hi, int32_t), FIELD(eps_lo, int32_t), FIELD(eps_hi, int32_t),
    FIELD(h_lo, int32_t), FIELD(h_hi, int32_t), FIELD(den_lo, int32_t),
    FIELD(den_hi, int32_t), FIELD(g_lo, int32_t), FIELD(g_hi, int32_t),
    FIELD(K_lo, int32_t), FIELD(K_hi, int32_t), FIELD(theta_lo, int32_t),
    FIELD(theta_hi, int32_t), FIELD(P_lo, int32_t), FIELD(P_hi, int32_t),
    FIELD(lam_lo, int32_t), FIELD(lam_hi, int32_t), FIELD(phi_ps, int32_t),
    FIELD(eps_ts, int32_t), FIELD(eps_os, int32_t), FIELD(h_os, int32_t),
    FIELD(s_os, int32_t), FIELD(sc_s, int32_t), FIELD(lam_den, int32_t),
    FIELD(one_den, int32_t), FIELD(dividend, int64_t), FIELD(gc_s, int32_t),
    FIELD(g_up, int32_t), FIELD(kg_bl, int32_t), FIELD(kg_max, int32_t),
    FIELD(theta_s, int32_t), FIELD(P_s, int32_t),
    FIELD(inv_lam, int32_t), FIELD(one_lam, int32_t), FIELD(c_s, int32_t),
    FIELD(trace_ps, int32_t), FIELD(trace_max_lam, int32_t),
    FIELD(trace_max_lim, int64_t), FIELD(tc_s, int32_t), FIELD(hc_s, int32_t),
    FIELD(vw_ps, int32_t), FIELD(lhs_ps, int32_t), FIELD(cmp_scale_diff, int32_t),
    FIELD(trace_hi, int32_t), FIELD(e_max, int32_t),
};
#define NFIELDS (sizeof fields / sizeof fields[0])

static int fail(const char *what)
{
    fprintf(stderr, "vector_driver: %s\n", what);
    return 2;
}

static int read_i64(FILE *f, long long *v)
{
    return fscanf(f, "%lld", v) == 1;
}

static int read_word(FILE *f, int32_t *v)
{
    long long x;
    if (!read_i64(f, &x) || x < INT32_MIN || x > INT32_MAX) {
        return 0;
    }
    *v = (int32_t)x;
    return 1;
}

int main(int argc, char **argv)
{
    static canrls_plan_q31 plan;
    static canrls_rls_q31 S;
    int32_t theta[CANRLS_N_MAX], P[CANRLS_TRI(CANRLS_N_MAX)], p0[CANRLS_N_MAX];
    int32_t P_frac[CANRLS_TRI(CANRLS_N_MAX)];
    uint32_t theta_frac[CANRLS_N_MAX];
    int32_t phi[CANRLS_N_MAX], e, c, y;
    char set[NFIELDS];
    char key[64];
    long long count, n, N, k, v;
    unsigned i, m;
    FILE *in, *out;

    if (argc != 3) {
        return fail("usage: vector_driver IN OUT");
    }
    in = fopen(argv[1], "r");
    out = fopen(argv[2], "w");
    if (in == NULL || out == NULL) {
        return fail("cannot open IN or OUT");
    }
    memset(set, 0, sizeof set);
    if (fscanf(in, "%63s", key) != 1 || strcmp(key, "plan") != 0 || !read_i64(in, &count)) {
        return fail("expected 'plan <count>'");
    }
    for (k = 0; k < count; k++) {
        if (fscanf(in, "%63s", key) != 1 || !read_i64(in, &v)) {
            return fail("malformed plan line");
        }
        for (i = 0; i < NFIELDS && strcmp(fields[i].name, key) != 0; i++) {
        }
        if (i == NFIELDS) {
            fprintf(stderr, "vector_driver: constant %s is not in canrls_plan_q31\n", key);
            return 2;
        }
        if (fields[i].size == sizeof(int32_t)) {
            int32_t w = (int32_t)v;
            if (v < INT32_MIN || v > INT32_MAX) {
                return fail("a 32-bit constant is out of range");
            }
            memcpy((char *)&plan + fields[i].offset, &w, sizeof w);
        } else {
            int64_t w = (int64_t)v;
            memcpy((char *)&plan + fields[i].offset, &w, sizeof w);
        }
        set[i] = 1;
    }
    for (i = 0; i < NFIELDS; i++) {
        if (!set[i]) {
            fprintf(stderr, "vector_driver: constant %s is missing\n", fields[i].name);
            return 2;
        }
    }
    if (fscanf(in, "%63s", key) != 1 || strcmp(key, "n") != 0 || !read_i64(in, &n)
        || n < 1 || n > CANRLS_N_MAX) {
        return fail("expected 'n <n>' within CANRLS_N_MAX");
    }
    m = (unsigned)CANRLS_TRI(n);
    if (fscanf(in, "%63s", key) != 1 || strcmp(key, "state") != 0) {
        return fail("expected 'state'");
    }
    for (i = 0; i < n; i++) {
        if (!read_word(in, &theta[i])) {
            return fail("malformed theta");
        }
    }
    for (i = 0; i < n; i++) {
        if (!read_i64(in, &v) || v < 0 || v > 0xFFFFFFFFLL) {
            return fail("malformed theta_frac");
        }
        theta_frac[i] = (uint32_t)v;
    }
    for (i = 0; i < m; i++) {
        if (!read_word(in, &P[i])) {
            return fail("malformed P");
        }
    }
    for (i = 0; i < m; i++) {
        if (!read_word(in, &P_frac[i])) {
            return fail("malformed P_frac");
        }
    }
    if (!read_word(in, &e) || !read_word(in, &c) || !read_i64(in, &v)) {
        return fail("malformed e, c or frozen");
    }
    /* init from the diagonal, then the full checkpoint */
    for (i = 0; i < n; i++) {
        p0[i] = P[canrls_tri_index((uint32_t)n, i, i)];
    }
    if (canrls_init_q31(&S, &plan, (uint32_t)n, p0, e) != CANRLS_OK) {
        return fail("canrls_init_q31 refused the state");
    }
    if (canrls_restore_q31(&S, theta, theta_frac, P, P_frac, e, c) != CANRLS_OK) {
        return fail("canrls_restore_q31 refused the state");
    }
    S.frozen = v != 0;
    for (i = 0; i < CANRLS_NSITES; i++) {
        long long x;
        if (!read_i64(in, &x) || x < 0) {
            return fail("malformed counts");
        }
        S.counts[i] = (uint32_t)x;
    }
    if (fscanf(in, "%63s", key) != 1 || strcmp(key, "steps") != 0 || !read_i64(in, &N)) {
        return fail("expected 'steps <N>'");
    }
    for (k = 0; k < N; k++) {
        canrls_step_q31 st;
        int applied;
        if (!read_i64(in, &v)) {
            return fail("malformed step");
        }
        S.frozen = v != 0;
        for (i = 0; i < n; i++) {
            if (!read_word(in, &phi[i])) {
                return fail("malformed phi");
            }
        }
        if (!read_word(in, &y)) {
            return fail("malformed y");
        }
        applied = canrls_update_q31(&S, phi, y, &st);
        fprintf(out, "%d %ld %ld %ld %lu", applied, (long)st.eps, (long)st.trace, (long)st.e,
                (unsigned long)st.flags);
        for (i = 0; i < n; i++) {
            fprintf(out, " %ld", (long)canrls_theta_q31(&S, i));
        }
        for (i = 0; i < n; i++) {
            fprintf(out, " %lu", (unsigned long)canrls_theta_frac_q31(&S, i));
        }
        for (i = 0; i < m; i++) {
            fprintf(out, " %ld", (long)canrls_P_q31(&S, i));
        }
        for (i = 0; i < m; i++) {
            fprintf(out, " %ld", (long)canrls_P_frac_q31(&S, i));
        }
        fprintf(out, " %ld", (long)S.c);
        for (i = 0; i < CANRLS_NSITES; i++) {
            fprintf(out, " %lu", (unsigned long)S.counts[i]);
        }
        fputc('\n', out);
    }
    fclose(in);
    return fclose(out) == 0 ? 0 : fail("cannot write OUT");
}
