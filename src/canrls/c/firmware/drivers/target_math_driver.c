/*
 * target_math_driver.c -- the arithmetic of canrls_target.c on given inputs, for
 * tests/firmware/test_target_math.py to hold against the Python specification (qmath).
 *
 * SPDX-License-Identifier: MIT
 *
 * It includes canrls_target.c to reach its static functions. stdin: one operation per
 * line, "name arg..." (decimal integers); stdout: one line of results per operation:
 *   mul_rsh x m s  |  clog2_mul a m  |  isqrt n  |  tanh z  |  tanh_wide z  |  exp x
 *   sincos phase
 *   f32 v e  |  svf a0 a1 g0 g1 x1 x2 up u fx  |  svf32 a0 a1 g0 g1 x1 x2 up u
 *   floor m e  |  ceil m e  |  rsh x s
 *   p64 word frac s lo hi  |  float bits width frac shift big_endian ("reject": not passed)
 */
#include <inttypes.h>
#include <stdio.h>
#include <string.h>

#include "canrls_target.c"

int main(void)
{
    char op[16];
    while (scanf("%15s", op) == 1) {
        if (strcmp(op, "mul_rsh") == 0) {
            int64_t x;
            int32_t m, s;
            if (scanf("%" SCNd64 " %" SCNd32 " %" SCNd32, &x, &m, &s) != 3) return 2;
            printf("%" PRId64 "\n", cr_mul_rsh(x, m, s));
        } else if (strcmp(op, "clog2_mul") == 0) {
            uint64_t a;
            uint32_t m;
            if (scanf("%" SCNu64 " %" SCNu32, &a, &m) != 2) return 2;
            printf("%" PRId32 "\n", cr_clog2_mul(a, m));
        } else if (strcmp(op, "isqrt") == 0) {
            int64_t n;
            if (scanf("%" SCNd64, &n) != 1) return 2;
            printf("%" PRId64 "\n", cr_isqrt(n));
        } else if (strcmp(op, "tanh") == 0) {
            int32_t z;
            if (scanf("%" SCNd32, &z) != 1) return 2;
            printf("%" PRId32 "\n", cr_tanh_q24(z));
        } else if (strcmp(op, "tanh_wide") == 0) {
            int64_t z;
            if (scanf("%" SCNd64, &z) != 1) return 2;
            printf("%" PRId32 "\n", cr_tanh_q24_wide(z));
        } else if (strcmp(op, "exp") == 0) {
            int64_t x;
            if (scanf("%" SCNd64, &x) != 1) return 2;
            printf("%" PRId32 "\n", cr_exp_neg_q24(x));
        } else if (strcmp(op, "sincos") == 0) {
            uint64_t ph;
            int32_t s, c;
            if (scanf("%" SCNu64, &ph) != 1) return 2;
            cr_sincos_q64(ph, &s, &c);
            printf("%" PRId32 " %" PRId32 "\n", s, c);
        } else if (strcmp(op, "f32") == 0) {
            int64_t v;
            int32_t e;
            if (scanf("%" SCNd64 " %" SCNd32, &v, &e) != 2) return 2;
            printf("%" PRIu32 "\n", cr_f32_bits(v, e));
        } else if (strcmp(op, "float") == 0) {
            uint64_t bits;
            uint32_t width, shift, big;
            int32_t frac, v = 0;
            canrls_field f;
            if (scanf("%" SCNu64 " %" SCNu32 " %" SCNd32 " %" SCNu32 " %" SCNu32,
                      &bits, &width, &frac, &shift, &big) != 5) return 2;
            memset(&f, 0, sizeof f);
            f.length = (uint8_t)width;
            f.is_float = 1u;
            f.frac = (int8_t)frac;
            f.shift = (uint8_t)shift;
            f.big_endian = (uint8_t)big;
            if (cr_float(&f, bits << shift, bits << shift, &v)) {
                printf("%" PRId32 "\n", v);
            } else {
                printf("reject\n");
            }
        } else if (strcmp(op, "svf32") == 0) {
            int32_t a0, a1, g0, g1, x1, x2, up, u;
            if (scanf("%" SCNd32 " %" SCNd32 " %" SCNd32 " %" SCNd32 " %" SCNd32 " %" SCNd32
                      " %" SCNd32 " %" SCNd32, &a0, &a1, &g0, &g1, &x1, &x2, &up, &u) != 8) {
                return 2;
            }
            printf("%" PRId32 "\n", cr_svf_row32(a0, a1, g0, g1, x1, x2, up, u));
        } else if (strcmp(op, "svf") == 0) {
            int32_t a[2], g0, g1, up, u, fx, uph, upl, uh, ul;
            int64_t x1, x2;
            if (scanf("%" SCNd32 " %" SCNd32 " %" SCNd32 " %" SCNd32 " %" SCNd64 " %" SCNd64
                      " %" SCNd32 " %" SCNd32 " %" SCNd32,
                      &a[0], &a[1], &g0, &g1, &x1, &x2, &up, &u, &fx) != 9) return 2;
            cr_split_input(up, fx, &uph, &upl);
            cr_split_input(u, fx, &uh, &ul);
            printf("%" PRId64 "\n", cr_svf_row(a[0], a[1], g0, g1, x1, x2, uph, upl, uh, ul));
        } else if (strcmp(op, "floor") == 0 || strcmp(op, "ceil") == 0) {
            uint64_t m;
            int32_t e;
            if (scanf("%" SCNu64 " %" SCNd32, &m, &e) != 2) return 2;
            printf("%" PRId64 "\n", cr_scaled(m, e, op[0] != 'f'));
        } else if (strcmp(op, "rsh") == 0) {
            int64_t x;
            int32_t s;
            if (scanf("%" SCNd64 " %" SCNd32, &x, &s) != 2) return 2;
            printf("%" PRId64 "\n", cr_rsh(x, s));
        } else if (strcmp(op, "p64") == 0) {
            int32_t w, f, s, lo, hi;
            uint32_t n = 0u;
            if (scanf("%" SCNd32 " %" SCNd32 " %" SCNd32 " %" SCNd32 " %" SCNd32,
                      &w, &f, &s, &lo, &hi) != 5) return 2;
            cr_P_scale(&w, &f, s, lo, hi, &n);
            printf("%" PRId32 " %" PRId32 " %" PRIu32 "\n", w, f, n);
        } else {
            return 2;
        }
    }
    return 0;
}
