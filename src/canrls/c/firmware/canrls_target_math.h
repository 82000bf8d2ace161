/*
 * canrls_target_math.h -- the integer arithmetic of the target's per-frame path, shared by
 * the table-driven canrls_target.c and the straight-line canrls_front.c that `canrls
 * export-c` generates for one model (the same functions, so the same integers).
 *
 * SPDX-License-Identifier: MIT
 *
 * Each function is the one of the same name (without cr_) in src/canrls/firmware/qmath.py
 * and spec.py. Integers only; a left shift is never applied to a negative value (a
 * multiplication by a power of two instead), and the arithmetic right shift of a negative
 * value is required (checked in canrls_target.c).
 */
#ifndef CANRLS_TARGET_MATH_H
#define CANRLS_TARGET_MATH_H

#include <stdint.h>

#include "canrls_fixed.h"
#include "canrls_target.h"
#include "canrls_target_tables.h"

#define ONE_Q30 ((int64_t)1 << 30)
#define I62 ((int64_t)1 << 62)
#define W_FRAC 16
#define Z_FRAC 24

/* ------------------------------------------------------------------ arithmetic */

/* hides what GCC knows of v's range (nothing is emitted): knowing a factor non-negative,
 * GCC multiplies it as unsigned (UMULL, MLA and a shift for the other's sign) where one
 * SMLAL does */
#if defined(__GNUC__)
#define CR_OPAQUE(v) __asm__("" : "+r"(v))
#else
#define CR_OPAQUE(v) ((void)0)
#endif

/* a function kept out of its caller: the caller's registers stay its own */
#if defined(__GNUC__)
#define CR_NOINLINE __attribute__((noinline))
#else
#define CR_NOINLINE
#endif

/* rsh(x, s) = (x + 2^(s-1)) >> s for s >= 0, as ((x >> (s-1)) + 1) >> 1: no overflow. */
static inline int64_t cr_rsh(int64_t x, int32_t s)
{
    if (s <= 0) {
        return x;
    }
    if (s >= 64) {
        return 0;
    }
    return ((x >> (s - 1)) + 1) >> 1;
}

/* rsh(x, s) of an int32 for 1 <= s <= 31: floor(x 2^-s) and the bit below it (half up) */
static inline int32_t cr_rsh32(int32_t x, int32_t s)
{
    return (x >> s) + ((x >> (s - 1)) & 1);
}

static inline int64_t cr_sat(int64_t x, int64_t lo, int64_t hi)
{
    return x < lo ? lo : x > hi ? hi : x;
}

/* x saturated to int32: the low word when x is its sign extension (one compare of the high
 * word), else the bound of x's sign */
static inline int32_t cr_sat32(int64_t x)
{
    const int32_t lo = (int32_t)x;
    if ((int64_t)lo == x) {
        return lo;
    }
    return x < 0 ? INT32_MIN : INT32_MAX;
}

/* x 2^s for s >= 0 without shifting a negative value (the caller bounds the result) */
static inline int64_t cr_shl(int64_t x, int32_t s)
{
    return x * ((int64_t)1 << s);
}

/* rsh(x m, s) saturated to +-2^62 (qmath.mul_rsh), |x| < 2^61, x = h 2^31 + l */
static inline int64_t cr_mul_rsh(int64_t x, int32_t m, int32_t s)
{
    /* h < 2^30 and l < 2^31: both words, each product one SMULL */
    const int64_t a = (int64_t)(int32_t)(x >> 31) * m;
    const int64_t b = (int64_t)(int32_t)(x & 0x7FFFFFFF) * m;
    if ((uint32_t)s - 32u <= 60u) {
        /* 32 <= s <= 92 (one unsigned compare): (T + 2^(s-32)) >> (s - 31) with
         * T = h m + (l m >> 31), as ((T >> (s - 32)) + 1) >> 1: one variable shift, no
         * 64-bit constant */
        return (((a + (b >> 31)) >> ((uint32_t)s - 32u)) + 1) >> 1;
    }
    if (s > 31) {
        return 0; /* s >= 93 */
    }
    if (s == 31) {
        /* h m + ((l m + 2^30) >> 31) */
        return a + ((b + ((int64_t)1 << 30)) >> 31);
    }
    /* s < 31: h m 2^(31-s) + rsh(l m, s), saturated */
    if (a >= ((int64_t)1 << (31 + s)) || -a >= ((int64_t)1 << (31 + s))) {
        return a >= 0 ? I62 : -I62;
    }
    return cr_sat(cr_shl(a, 31 - s) + cr_rsh(b, s), -I62, I62);
}

/* the piecewise cubic of a table at u / 2^32, Q30: p = c3; p = c_i + rsh(p t, 31) */
static inline int32_t cr_table_eval(const int32_t (*table)[4], int32_t k, uint32_t u)
{
    const int32_t *c = table[u >> (32 - k)];
    /* t = position in the segment, Q31 */
    int32_t t = (int32_t)((uint32_t)(u << k) >> 1);
    /* p = c3; p = c_i + rsh(p t, 31): the words of the tables keep p within int32 */
    int32_t p = c[3];
    CR_OPAQUE(t);
    p = c[2] + (int32_t)(((int64_t)p * t + ((int64_t)1 << 30)) >> 31);
    p = c[1] + (int32_t)(((int64_t)p * t + ((int64_t)1 << 30)) >> 31);
    p = c[0] + (int32_t)(((int64_t)p * t + ((int64_t)1 << 30)) >> 31);
    return p;
}

/* tanh(z 2^-24), Q30: odd, 1 from |z| >= 8 */
static inline int32_t cr_tanh_q24(int32_t z)
{
    const uint32_t a = z < 0 ? 0u - (uint32_t)z : (uint32_t)z;
    const int32_t v = a >= (8u << 24) ? (int32_t)ONE_Q30
                                      : cr_table_eval(cr_tanh, CR_TANH_LOG2, a << 5);
    return z < 0 ? -v : v;
}

/* tanh(z 2^-24), Q30, of z not saturated: cr_tanh_q24 of z saturated to int32 (both +-1
 * from |z| >= 8), without the saturation */
static inline int32_t cr_tanh_q24_wide(int64_t z)
{
    if (z >= ((int64_t)8 << 24)) {
        return (int32_t)ONE_Q30;
    }
    if (z <= -((int64_t)8 << 24)) {
        return -(int32_t)ONE_Q30;
    }
    return cr_tanh_q24((int32_t)z);
}

/* 2^(-x 2^-24), Q30, x >= 0 */
static inline int32_t cr_exp2_neg_q24(int64_t x)
{
    const int64_t n = x >> 24;
    if (n >= 31) {
        return 0;
    }
    return (int32_t)cr_rsh(cr_table_eval(cr_exp2, CR_EXP2_LOG2,
                                         (uint32_t)(x & 0xFFFFFF) << 8), (int32_t)n);
}

/* exp(-x 2^-24) = 2^(-x log2 e), Q30 */
static inline int32_t cr_exp_neg_q24(int64_t x)
{
    return cr_exp2_neg_q24(cr_rsh(x * 1549082005, 30));
}

/* S(x) or S(~x) of the quadrant q, signed by it */
static inline int32_t cr_quarter(uint32_t q, uint32_t x)
{
    const int32_t v = cr_table_eval(cr_sin, CR_SIN_LOG2, (q & 1u) == 0u ? x : ~x);
    return q < 2u ? v : -v;
}

/* sin and cos of 2 pi phase / 2^64, Q30 */
static inline void cr_sincos_q64(uint64_t phase, int32_t *s, int32_t *c)
{
    const uint32_t q = (uint32_t)(phase >> 62);
    const uint32_t x = (uint32_t)(phase >> 30);
    *s = cr_quarter(q, x);
    *c = cr_quarter((q + 1u) & 3u, x);
}


/* the bytes of a word in the other order (one REV where the compiler sees it) */
static inline uint32_t cr_bswap32(uint32_t w)
{
    return (w >> 24) | ((w >> 8) & 0xFF00u) | ((w << 8) & 0xFF0000u) | (w << 24);
}

/* a float field's value times 2^frac, rounded half away from zero, in *v (qmath.float_fixed),
 * from its payload word shifted to the field (a binary64 when wide, else the low 32 bits):
 * 0 for NaN, infinity and a value beyond +-(2^31 - 1) (outside every float field's lo..hi) */
static inline int cr_float_word(uint64_t word, int wide, int32_t frac, int32_t *v)
{
    const uint64_t bits = wide ? word : word & 0xFFFFFFFFu;
    const int32_t mb = wide ? 52 : 23;                 /* stored mantissa bits */
    const int32_t emax = wide ? 2047 : 255;            /* NaN and infinity */
    const int32_t e = (int32_t)(bits >> mb) & emax;
    uint64_t M = bits & ((UINT64_C(1) << mb) - 1u);
    uint64_t mag;
    int32_t s;
    if (e == emax) {
        return 0;
    }
    /* v 2^frac = M 2^s: M with its hidden bit, s = max(e, 1) - bias - mb + frac */
    if (e != 0) {
        M |= UINT64_C(1) << mb;
    }
    s = (e != 0 ? e : 1) - (emax >> 1) - mb + frac;
    if (s >= 0) {
        /* |raw| = M 2^s: beyond 2^62 (then beyond 32 bits) when s > 62 - mb, M != 0 */
        if (M != 0u && s > 62 - mb) {
            return 0;
        }
        mag = M << s;
    } else {
        /* |raw| = rsh(M, -s), round half up; 0 when -s > mb + 1 > log2 M + 1 */
        mag = -s > mb + 1 ? 0u : (M + (UINT64_C(1) << (-s - 1))) >> -s;
    }
    if (mag > 0x7FFFFFFFu) {
        return 0;
    }
    *v = ((bits >> (wide ? 63 : 31)) & 1u) != 0u ? -(int32_t)mag : (int32_t)mag;
    return 1;
}

/* the E2E CRC-8 table (polynomial 0x1D, canrls.can.e2e.CRC8_TABLE) */
static const uint8_t cr_crc8[256] = {
    0x00, 0x1D, 0x3A, 0x27, 0x74, 0x69, 0x4E, 0x53, 0xE8, 0xF5, 0xD2, 0xCF, 0x9C, 0x81, 0xA6, 0xBB,
    0xCD, 0xD0, 0xF7, 0xEA, 0xB9, 0xA4, 0x83, 0x9E, 0x25, 0x38, 0x1F, 0x02, 0x51, 0x4C, 0x6B, 0x76,
    0x87, 0x9A, 0xBD, 0xA0, 0xF3, 0xEE, 0xC9, 0xD4, 0x6F, 0x72, 0x55, 0x48, 0x1B, 0x06, 0x21, 0x3C,
    0x4A, 0x57, 0x70, 0x6D, 0x3E, 0x23, 0x04, 0x19, 0xA2, 0xBF, 0x98, 0x85, 0xD6, 0xCB, 0xEC, 0xF1,
    0x13, 0x0E, 0x29, 0x34, 0x67, 0x7A, 0x5D, 0x40, 0xFB, 0xE6, 0xC1, 0xDC, 0x8F, 0x92, 0xB5, 0xA8,
    0xDE, 0xC3, 0xE4, 0xF9, 0xAA, 0xB7, 0x90, 0x8D, 0x36, 0x2B, 0x0C, 0x11, 0x42, 0x5F, 0x78, 0x65,
    0x94, 0x89, 0xAE, 0xB3, 0xE0, 0xFD, 0xDA, 0xC7, 0x7C, 0x61, 0x46, 0x5B, 0x08, 0x15, 0x32, 0x2F,
    0x59, 0x44, 0x63, 0x7E, 0x2D, 0x30, 0x17, 0x0A, 0xB1, 0xAC, 0x8B, 0x96, 0xC5, 0xD8, 0xFF, 0xE2,
    0x26, 0x3B, 0x1C, 0x01, 0x52, 0x4F, 0x68, 0x75, 0xCE, 0xD3, 0xF4, 0xE9, 0xBA, 0xA7, 0x80, 0x9D,
    0xEB, 0xF6, 0xD1, 0xCC, 0x9F, 0x82, 0xA5, 0xB8, 0x03, 0x1E, 0x39, 0x24, 0x77, 0x6A, 0x4D, 0x50,
    0xA1, 0xBC, 0x9B, 0x86, 0xD5, 0xC8, 0xEF, 0xF2, 0x49, 0x54, 0x73, 0x6E, 0x3D, 0x20, 0x07, 0x1A,
    0x6C, 0x71, 0x56, 0x4B, 0x18, 0x05, 0x22, 0x3F, 0x84, 0x99, 0xBE, 0xA3, 0xF0, 0xED, 0xCA, 0xD7,
    0x35, 0x28, 0x0F, 0x12, 0x41, 0x5C, 0x7B, 0x66, 0xDD, 0xC0, 0xE7, 0xFA, 0xA9, 0xB4, 0x93, 0x8E,
    0xF8, 0xE5, 0xC2, 0xDF, 0x8C, 0x91, 0xB6, 0xAB, 0x10, 0x0D, 0x2A, 0x37, 0x64, 0x79, 0x5E, 0x43,
    0xB2, 0xAF, 0x88, 0x95, 0xC6, 0xDB, 0xFC, 0xE1, 0x5A, 0x47, 0x60, 0x7D, 0x2E, 0x33, 0x14, 0x09,
    0x7F, 0x62, 0x45, 0x58, 0x0B, 0x16, 0x31, 0x2C, 0x97, 0x8A, 0xAD, 0xB0, 0xE3, 0xFE, 0xD9, 0xC4,
};

/* an input u 2^fx as h 2^31 + l (0 <= l < 2^31): the C's form of the input term */
static inline void cr_split_input(int32_t u, int32_t fx, int32_t *h, int32_t *l)
{
    if (fx >= 31) {
        /* |u| 2^fx < 2^59 (the model's fx): h = u 2^(fx-31) is a word, l = 0 */
        *h = u * (int32_t)((uint32_t)1 << (fx - 31));
        *l = 0;
    } else {
        *h = u >> (31 - fx);
        *l = (int32_t)(((uint32_t)u & ((1u << (31 - fx)) - 1u)) << fx);
    }
}

/* rsh(a0 x1 + a1 x2 + (g0 u[k-1] + g1 u[k]) 2^fx, 30) with |x| < 2^60: every term as
 * h 2^30 + l, summed as H 2^30 + L (each product one SMULL or SMLAL), so the result is
 * H + rsh(L, 30). A state splits as x = (x >> 30) 2^30 + l (0 <= l < 2^30), an input's
 * words as h 2^31 + l = 2h 2^30 + l: 2g h in H (|2g| <= 2^31, the model's |g| <= 2^30;
 * one SMLAL where the compiler sees 2g a word). The model bounds |a0| + |a1| + |g0| + |g1|
 * below 2^31, so |L| < 2^62 and |H| < 2^62. */
static inline int64_t cr_svf_row(int32_t a0, int32_t a1, int32_t g0, int32_t g1, int64_t x1,
                                 int64_t x2, int32_t uph, int32_t upl, int32_t uh, int32_t ul)
{
    const int64_t H = (int64_t)a0 * (int32_t)(x1 >> 30) + (int64_t)a1 * (int32_t)(x2 >> 30)
                      + 2 * (int64_t)g0 * uph + 2 * (int64_t)g1 * uh;
    const int64_t L = (int64_t)a0 * (int32_t)(x1 & 0x3FFFFFFF)
                      + (int64_t)a1 * (int32_t)(x2 & 0x3FFFFFFF)
                      + (int64_t)g0 * upl + (int64_t)g1 * ul;
    return H + ((L + ((int64_t)1 << 29)) >> 30);
}

/* a filter with 32-bit states (target_model.Filter.narrow): an input bounded by 1 (Q30)
 * with no fraction bit more (fx 0); each row's result is saturated to int32 */
static inline int cr_narrow(const canrls_filter *f)
{
    return (f->kind == CANRLS_SRC_TANH || f->kind == CANRLS_SRC_STRIBECK
            || f->kind == CANRLS_SRC_SIN || f->kind == CANRLS_SRC_COS) && f->fx == 0;
}

/* the row of a narrow filter, cr_svf_row at fx 0 on int32 words (states, the last input
 * and this one): rsh(a0 x1 + a1 x2 + g0 up + g1 u, 30) saturated to int32, four SMULL or
 * SMLAL (|sum| < 2^31 2^31, the model's row bound) */
static inline int32_t cr_svf_row32(int32_t a0, int32_t a1, int32_t g0, int32_t g1, int32_t x1,
                                   int32_t x2, int32_t up, int32_t u)
{
    const int64_t sum = (int64_t)a0 * x1 + (int64_t)a1 * x2 + (int64_t)g0 * up
                        + (int64_t)g1 * u;
    return cr_sat32((sum + ((int64_t)1 << 29)) >> 30);
}

/* ------------------------------------------------------------------ the per-sample steps
 * (the table-driven canrls_target.c calls them with the model's values, the generated
 * canrls_front.c with constants, so the compiler unrolls and folds them) */

static inline uint32_t cr_popcount(uint32_t v)
{
    uint32_t n = 0u;
    while (v != 0u) {
        n += v & 1u;
        v >>= 1;
    }
    return n;
}

/* pair a decoded frame (its message's bit, its key: the alive counter or -1) into the open
 * period of at most tol ticks; 0: dropped as a second frame of its message in the period */
static inline int cr_pair(canrls_target *S, uint32_t bit, int32_t key, int32_t tol, uint32_t t)
{
    if (S->open_mask != 0u) {
        const int same = (int32_t)(t - S->open_t) <= tol && key == S->open_counter;
        if (same && (S->open_mask & bit) != 0u) {
            /* a second frame of this message in the period: dropped */
            S->rejects[CANRLS_R_DUPLICATED]++;
            S->frame_loss = 1u;
            return 0;
        }
        if (!same) {
            /* another period began: the open one stays incomplete */
            S->rejects[CANRLS_R_UNPAIRED] += cr_popcount(S->open_mask);
            S->frame_loss = 1u;
            S->open_mask = 0u;
        }
    }
    if (S->open_mask == 0u) {
        S->open_t = t;
        S->open_counter = key;
    }
    S->open_mask |= bit;
    return 1;
}

/* the kernel's update of one equation with its columns and output as int32 words (saturated
 * by the caller), its flags and the residual's running mean square */
static inline void cr_step(canrls_target_eq *q, const int32_t *phq, int32_t yq,
                           int32_t rms_shift)
{
    canrls_step_q31 st;
    (void)canrls_update_q31(&q->rls, phq, yq, &st);
    q->updates++;
    q->flags |= st.flags;
    /* the residual's mean square: ms <- ms + (eps^2 - ms) >> rms_shift */
    q->ms += ((int64_t)st.eps * st.eps - q->ms) >> rms_shift;
}

/* count a processed sample; CANRLS_SAMPLE, with CANRLS_PUBLISH every `every` samples */
static inline uint32_t cr_sampled(canrls_target *S, uint32_t every)
{
    S->samples++;
    S->since_publish++;
    if (S->since_publish >= every) {
        S->since_publish = 0u;
        return CANRLS_SAMPLE | CANRLS_PUBLISH;
    }
    return CANRLS_SAMPLE;
}

#endif /* CANRLS_TARGET_MATH_H */
