/*
 * pass_driver.c -- the fixed-n kernel's pass over P and its windup test on given inputs,
 * for tests/firmware/test_ckernel.py to hold against the Python specification.
 *
 * SPDX-License-Identifier: MIT
 *
 * Built with -DCANRLS_N=n (the fixed-n kernel: its classes of the pass are compiled only
 * there); it includes canrls_fixed.c to reach its static functions. stdin: one operation
 * per line (decimal integers); stdout: one line of results per operation:
 *   pass P_s sh K[n] h[n] (word frac)[n(n+1)/2]
 *       the off-diagonal V_ij -= u(K_i h~_j) and every V_ij <- V_ij 2^sh (the diagonal
 *       shifted only), through the class canrls_update_q31 takes for P_s (PM_LOWK where
 *       K 2^a and h~ 2^b are words): the words and fractions after, then the count
 *   windup lam_den den_lo den_hi P_hi lhs_ps cmp_scale_diff hc_s vw_ps c e T sv h[n]
 *       windup_up's answer, 0 or 1
 */
#include <inttypes.h>
#include <stdio.h>
#include <string.h>

#include "canrls_fixed.c"

#if !CANRLS_FAST
#error "pass_driver.c needs the fixed-n kernel: -DCANRLS_N=n, not built for size"
#endif

#define M (CANRLS_N * (CANRLS_N + 1) / 2)

static int read_i32(int32_t *v, uint32_t count)
{
    uint32_t i;
    for (i = 0; i < count; i++) {
        if (scanf("%" SCNd32, &v[i]) != 1) {
            return 0;
        }
    }
    return 1;
}

static int op_pass(void)
{
    int32_t P_s, sh, K[CANRLS_N], h[CANRLS_N], Kk[CANRLS_N], hk[CANRLS_N], wf[2 * M];
    const int32_t *KP = K, *hP = h;
    canrls_P64 P[M];
    uint32_t i, mK = 0, mh = 0, c_P = 0;
    int mode;
    if (scanf("%" SCNd32 " %" SCNd32, &P_s, &sh) != 2 || !read_i32(K, CANRLS_N)
        || !read_i32(h, CANRLS_N) || !read_i32(wf, 2 * M) || P_s < 1 || P_s > 62 || sh < 0
        || sh > 30) {
        return 0;
    }
    for (i = 0; i < M; i++) {
        P[i].word = wf[2 * i];
        P[i].lo = (uint32_t)wf[2 * i + 1] ^ 0x80000000u;
    }
    /* the class of P_s, as KP_core takes it */
    mode = P_s >= 33 ? PM_HIGH : P_s == 32 ? PM_32 : PM_LOW;
    if (mode == PM_LOW) {
        int32_t a, b;
        for (i = 0; i < CANRLS_N; i++) {
            mK |= (uint32_t)(K[i] ^ (K[i] >> 31)) - (uint32_t)(K[i] >> 31);
            mh |= (uint32_t)(h[i] ^ (h[i] >> 31));
        }
        if (lowk_split(mK, mh, P_s, &a, &b)) {
            for (i = 0; i < CANRLS_N; i++) {
                Kk[i] = lowk_kword(K[i], a);
                hk[i] = (int32_t)((uint32_t)h[i] << b);
            }
            KP = Kk;
            hP = hk;
            mode = PM_LOWK;
        }
    }
    (void)P_off_any(P, KP, hP, mode, mode == PM_HIGH ? neg_pow2(P_s) : 0, P_s, sh, 0, &c_P);
    for (i = 0; i < M; i++) {
        printf("%" PRId32 " %" PRId32 " ", P[i].word, (int32_t)(P[i].lo ^ 0x80000000u));
    }
    printf("%" PRIu32 "\n", c_P);
    return 1;
}

static int op_windup(void)
{
    canrls_plan_q31 p;
    canrls_rls_q31 S;
    int32_t v[10], sv;
    int64_t T;
    memset(&p, 0, sizeof p);
    memset(&S, 0, sizeof S);
    if (!read_i32(v, 8) || scanf("%" SCNd32 " %" SCNd32 " %" SCNd64 " %" SCNd32, &S.c, &S.e,
                                 &T, &sv) != 4 || !read_i32(S.h, CANRLS_N) || T <= 0) {
        return 0;
    }
    p.lam_den = v[0];
    p.den_lo = v[1];
    p.den_hi = v[2];
    p.P_hi = v[3];
    p.lhs_ps = v[4];
    p.cmp_scale_diff = v[5];
    p.hc_s = v[6];
    p.vw_ps = v[7];
    S.plan = &p;
    S.n = CANRLS_N;
    printf("%d\n", windup_up(&S, T, sv));
    return 1;
}

int main(void)
{
    char op[16];
    while (scanf("%15s", op) == 1) {
        if (strcmp(op, "pass") == 0 ? !op_pass() : strcmp(op, "windup") == 0 ? !op_windup() : 1) {
            fprintf(stderr, "pass_driver: bad operation %s\n", op);
            return 2;
        }
    }
    return 0;
}
