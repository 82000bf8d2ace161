/*
 * canrls_fixed.c -- fixed-point recursive least squares, the embedded kernel.
 *
 * SPDX-License-Identifier: MIT
 *
 * Line for line the symmetric form of the Python specification
 * (canrls.estimation.fixed.kernels.fixed_block): the same names, the same order of
 * operations, the equation beside each line. See canrls_fixed.h for the numbers.
 */
#include "canrls_fixed.h"

#include <string.h>

/* The kernel needs an arithmetic (floor) right shift of negative values, which C99
 * leaves to the implementation; every compiler for a DSP or a microcontroller has it.
 * Refuse to build where it is missing. */
typedef char canrls_needs_arithmetic_shift[((-8 >> 1) == -4) ? 1 : -1];
typedef char canrls_needs_arithmetic_shift64[(((int64_t)-8 >> 1) == -4) ? 1 : -1];

/* Built for size: CANRLS_SMALL (canrls_fixed.h), see below. */

/* The helpers below are meant to disappear into their callers (the shift class of
 * mul_rsh must be a constant there); GCC and Clang are told so, except when built for
 * size: each helper is then one function out of line, called (less code than GCC's own
 * choice at -Os: 4574 B against 4868 B of canrls_fixed.o at n = 6). */
#if defined(__GNUC__)
#if CANRLS_SMALL
#define INLINE static __attribute__((noinline))
#else
#define INLINE static inline __attribute__((always_inline))
#endif
#define NOINLINE static __attribute__((noinline))
#define LIKELY(x) __builtin_expect(!!(x), 1)
#define UNLIKELY(x) __builtin_expect(!!(x), 0)
#else
#define INLINE static inline
#define NOINLINE static
#define LIKELY(x) (x)
#define UNLIKELY(x) (x)
#endif

/* out of line when built for size, else the compiler's choice */
#if CANRLS_SMALL && defined(__GNUC__)
#define SMALL_NOINLINE static __attribute__((noinline))
#else
#define SMALL_NOINLINE static
#endif

/* a rare part of the update: out of line where speed is asked (its registers kept off the
 * common path's), in its caller when built for size */
#if CANRLS_SMALL
#define RARE static inline
#else
#define RARE NOINLINE
#endif

/* n: the instance's, or the constant CANRLS_N where the build fixes it (-DCANRLS_N=6:
 * the loops over n unrolled, h~ summed row by row; canrls_init_q31 then takes only
 * n = CANRLS_N) */
#ifdef CANRLS_N
typedef char canrls_n_within_n_max[(CANRLS_N >= 1 && CANRLS_N <= CANRLS_N_MAX) ? 1 : -1];
#define NPAR(S) ((uint32_t)CANRLS_N)
#else
#define NPAR(S) ((S)->n)
#endif

/* Built for size (CANRLS_SMALL): loops, one general instance of each step, no
 * straight-line code (the same integers). Else, at a fixed n, CANRLS_FAST: the steps
 * unrolled for that n (docs/fixed_point.md, "A fixed n"). */
#if defined(CANRLS_N) && !CANRLS_SMALL
#define CANRLS_FAST 1
#else
#define CANRLS_FAST 0
#endif

/* loops over n unrolled completely where n is a constant and speed is asked (CANRLS_FAST) */
#if CANRLS_FAST && defined(__GNUC__) && !defined(__clang__)
#define UNROLL _Pragma("GCC unroll 16")
#elif CANRLS_FAST && defined(__clang__)
#define UNROLL _Pragma("unroll")
#else
#define UNROLL
#endif

/* A compiler barrier (GCC): words kept in memory are read from it again after it, not
 * held in registers (and spilled) across a stretch that does not need them */
#if defined(__GNUC__)
#define MEM_BARRIER() __asm__ volatile("" ::: "memory")
#else
#define MEM_BARRIER() ((void)0)
#endif

/* x computed here, in registers (GCC): its operations not moved past this point */
#if defined(__GNUC__)
#define KEEP_REG(x) __asm__("" : "+r"(x))
#else
#define KEEP_REG(x) ((void)0)
#endif

/* ------------------------------------------------------------------ the plan */

/* The constant plan. An export whose model has one equation defines CANRLS_PLAN_CONST
 * (in its canrls_bounds.h) as that equation's plan: the kernel then reads the plan from
 * this copy, which the compiler folds into the code (each shift, range and constant an
 * immediate), and canrls_init_q31 refuses any other plan. trace_max_lam alone is read
 * from the instance's plan: the target moves it with the prior (canrls_target.c). A
 * build without it (the package's extensions), or with -DCANRLS_PLAN_RUNTIME, reads
 * every constant from the instance's plan: any plan, the same integers. */
#if defined(CANRLS_PLAN_CONST) && !defined(CANRLS_PLAN_RUNTIME)
#define PLAN_IS_CONST 1
static const canrls_plan_q31 plan_const = CANRLS_PLAN_CONST;
#define PLAN(S) (&plan_const)
#else
#define PLAN_IS_CONST 0
#define PLAN(S) ((S)->plan)
#endif

/* ------------------------------------------------------- Q-format arithmetic */

/* rsh(x, s) = x / 2^s rounded half up, (x + 2^(s-1)) >> s, for 0 <= s <= 62
 * (Python _rsh; the caller guarantees |x| + 2^(s-1) < 2^63). */
INLINE int64_t rsh(int64_t x, int32_t s)
{
    return s > 0 ? (x + ((int64_t)1 << (s - 1))) >> s : x;
}

/* rsh of a word: ((x >> (s-1)) + 1) >> 1 equals (x + 2^(s-1)) >> s and cannot overflow. */
INLINE int32_t rsh32(int32_t x, int32_t s)
{
    return s > 0 ? ((x >> (s - 1)) + 1) >> 1 : x;
}

/* How rsh(x, s) is computed on a 32-bit machine (all three give the same integers):
 * SHIFT_ANY  any 0 <= s <= 62: the 64-bit formula;
 * SHIFT_LOW  1 <= s <= 31: x + 2^(s-1) in two words, shifted as two words, and the
 *            result a word in the common case;
 * SHIFT_HIGH s >= 32: the high word of x + 2^(s-1) shifted by s - 32: always a word.
 * Where the class is a constant (an inline loop called once per class), the compiler
 * makes one loop per class and the choice is made once per step, not per element. */
enum { SHIFT_ANY = 0, SHIFT_LOW = 1, SHIFT_HIGH = 2, SHIFT_32 = 3 };
/* P_step only: the class of the step's P_s decided in the loop (one instance, CANRLS_SMALL) */
enum { SHIFT_VAR = 4 };

/* SHIFT_32: s = 32 exactly (rounded in the low word); SHIFT_HIGH: 33 <= s <= 62 */
INLINE int shift_class(int32_t s)
{
    return s >= 33 ? SHIFT_HIGH : s == 32 ? SHIFT_32 : s >= 1 ? SHIFT_LOW : SHIFT_ANY;
}

/* rsh(x, s) = (x + 2^(s-1)) >> s, computed as its class says */
INLINE int64_t rsh_c(int64_t x, int32_t s, int cls)
{
    if (cls == SHIFT_HIGH || cls == SHIFT_32) {
        const uint64_t u = (uint64_t)x + ((uint64_t)1 << (s - 1));
        return (int32_t)(uint32_t)(u >> 32) >> (s - 32);
    }
    if (cls == SHIFT_LOW) {
        const uint64_t u = (uint64_t)x + (uint32_t)((uint32_t)1 << (s - 1)); /* s <= 31 */
        const uint32_t lo = (uint32_t)u;
        const int32_t hi = (int32_t)(uint32_t)(u >> 32);
        const uint32_t rlo = (lo >> s) | ((uint32_t)hi << (32 - s));
        const int32_t rhi = hi >> s;
        if (rhi == ((int32_t)rlo >> 31)) {
            return (int32_t)rlo; /* the result fits a word: the common case */
        }
        return (int64_t)(((uint64_t)(uint32_t)rhi << 32) | rlo);
    }
    return rsh(x, s);
}

/* a b, the exact product of two words (one SMULL: written out on Thumb-2, where GCC
 * otherwise keeps the sign word of a long-lived c and multiplies 64 x 64) */
INLINE int64_t mul_ww(int32_t a, int32_t b)
{
#if defined(__GNUC__) && defined(__thumb2__)
    uint32_t lo, hi;
    __asm__("smull %0, %1, %2, %3" : "=&r"(lo), "=&r"(hi) : "r"(a), "r"(b));
    return (int64_t)(((uint64_t)hi << 32) | lo);
#else
    return (int64_t)a * b;
#endif
}

/* rsh(x, s) for any 0 <= s <= 62, the half added in one word when 1 <= s <= 31 */
INLINE int64_t rsh_w(int64_t x, int32_t s)
{
    if ((uint32_t)(s - 1) < 31u) {
        return (int64_t)((uint64_t)x + (uint32_t)((uint32_t)1 << (s - 1))) >> s;
    }
    return rsh(x, s);
}

/* rsh(a b, s): a product of two words rounded half up by s bits */
INLINE int64_t mul_rsh(int32_t a, int32_t b, int32_t s, int cls)
{
    return rsh_c((int64_t)a * b, s, cls);
}

/* sat(x) = x clamped to [lo, hi]; a clamp increments *n (Python saturate). */
INLINE int32_t sat(int64_t x, int32_t lo, int32_t hi, uint32_t *n)
{
    /* the common case in 32-bit compares: x fits a word and lies in [lo, hi] */
    if ((int64_t)(int32_t)x == x
        && (uint32_t)(int32_t)x - (uint32_t)lo <= (uint32_t)hi - (uint32_t)lo) {
        return (int32_t)x;
    }
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

/* A word r (already a word: an int32_t) clamped to [lo, hi], counted. */
INLINE int32_t clamp32(int32_t r, int32_t lo, int32_t hi, uint32_t *n)
{
    if (LIKELY((uint32_t)r - (uint32_t)lo <= (uint32_t)hi - (uint32_t)lo)) {
        return r;
    }
    *n += 1u;
    return r > hi ? hi : lo;
}

/* sat(x) for a 64-bit x given as its two words: the common case in 32-bit compares */
INLINE int32_t sat2(int32_t rhi, uint32_t rlo, int32_t lo, int32_t hi, uint32_t *n)
{
    if (LIKELY(rhi == ((int32_t)rlo >> 31))) {
        return clamp32((int32_t)rlo, lo, hi, n); /* x fits a word */
    }
    *n += 1u;
    return rhi < 0 ? lo : hi;
}

/* sat(a + b) of two words, counted (a + b computed without overflow); ``full``: the word
 * is the whole int32_t (lo = INT32_MIN, hi = INT32_MAX), a constant at each call */
INLINE int32_t add_sat(int32_t a, int32_t b, int32_t lo, int32_t hi, uint32_t *n, int full)
{
#if defined(__GNUC__)
    int32_t r;
    if (UNLIKELY(__builtin_add_overflow(a, b, &r))) {
        *n += 1u;
        return b > 0 ? hi : lo;
    }
    return full ? r : clamp32(r, lo, hi, n);
#else
    (void)full;
    return sat((int64_t)a + b, lo, hi, n);
#endif
}

/* acc + a b (one SMLAL) */
INLINE uint64_t mla_ww(uint64_t acc, int32_t a, int32_t b)
{
#if defined(__GNUC__) && defined(__thumb2__)
    /* (the accumulator one 64-bit operand: a register pair, as LDRD and STRD take it) */
    __asm__("smlal %Q0, %R0, %1, %2" : "+r"(acc) : "r"(a), "r"(b));
    return acc;
#else
    return acc + (uint64_t)((int64_t)a * b);
#endif
}

/* rsh(a b, 32): the high word of a b + 2^31 (one SMMULR on a core with the DSP
 * extension) */
INLINE int32_t mul_rsh32(int32_t a, int32_t b)
{
#if defined(__GNUC__) && defined(__ARM_FEATURE_DSP) && defined(__thumb2__)
    int32_t r;
    __asm__("smmulr %0, %1, %2" : "=r"(r) : "r"(a), "r"(b));
    return r;
#else
    return (int32_t)(uint32_t)(((uint64_t)((int64_t)a * b) + ((uint64_t)1 << 31)) >> 32);
#endif
}

/* The 64-bit estimate (Python _theta_add): q = word 2^32 + frac (canrls_theta64: the word
 * t, its fraction f in units of 2^-32 LSB) += floor(p 2^(32-s)) for s < 32 and
 * floor(p / 2^32) 2^(64-s) (the high word of p, exact at this scale) for 32 <= s <= 62,
 * saturated to [lo 2^32, hi 2^32 + 2^32 - 1] (counted). The general case (any s, any
 * theta word). */
INLINE void theta_add(canrls_theta64 *q, int64_t p, int32_t s, int32_t lo, int32_t hi,
                      uint32_t *n)
{
    const int64_t whole = p >> s; /* floor(p / 2^s): whole LSBs */
    /* the 32 bits below the LSB: s >= 32, of the high word of p (p's low word dropped);
     * s < 32, p mod 2^s moved up */
    const uint32_t part = s >= 32 ? (uint32_t)((uint64_t)(p >> 32) << (64 - s))
                                  : (uint32_t)((uint64_t)p << (32 - s));
    const uint64_t fs = (uint64_t)q->frac + part;
    const int64_t x = (int64_t)q->word + whole + (int64_t)(fs >> 32);
    if (UNLIKELY(x > hi)) {
        *n += 1u;
        q->frac = 0xFFFFFFFFu;
        q->word = hi;
        return;
    }
    if (UNLIKELY(x < lo)) {
        *n += 1u;
        q->frac = 0u;
        q->word = lo;
        return;
    }
    q->frac = (uint32_t)fs;
    q->word = (int32_t)x;
}

/* -2^(64-s) for 33 <= s <= 62: a word (-2^31 at s = 33, where 2^(64-s) is not one) */
INLINE int32_t neg_pow2(int32_t s)
{
    return (int32_t)(0xFFFFFFFFu << (64 - s));
}

/* theta_add for 33 <= s <= 62 and the whole int32_t word: q as one int64_t plus the high
 * word ph of the product at 2^-32 LSB, ph 2^(64-s) = -(ph nm) (nm = neg_pow2(s): one
 * SMULL), saturated where the 64-bit sum overflows, which is exactly where the word leaves
 * the int32_t. (Written on the two words, not on an int64_t array: GCC then branches on
 * the overflow flag of SBCS instead of materialising it, and loads and stores the pair
 * with LDRD/STRD.) */
INLINE void theta_add_full(canrls_theta64 *q, int32_t ph, int32_t nm, int32_t s, uint32_t *n)
{
#if defined(__GNUC__)
    const int64_t t = (int64_t)(((uint64_t)(uint32_t)q->word << 32) | q->frac);
    int64_t x;
    if (UNLIKELY(__builtin_sub_overflow(t, mul_ww(ph, nm), &x))) {
        *n += 1u;
        q->frac = ph > 0 ? 0xFFFFFFFFu : 0u;
        q->word = ph > 0 ? INT32_MAX : INT32_MIN;
        return;
    }
    (void)s;
    q->frac = (uint32_t)x;
    q->word = (int32_t)(x >> 32);
#else
    (void)nm;
    theta_add(q, (int64_t)ph * 4294967296LL, s, INT32_MIN, INT32_MAX, n);
#endif
}

#if defined(__GNUC__) && CANRLS_FAST
/* theta_q + a b at 2^-32 LSB (the product exact in 64 bits), saturated where the sum leaves
 * the whole int32_t word (counted): the update K eps 2^(32 - s) of a shift s <= 31 with
 * a = K 2^(32 - s) a word (theta_add's integers); only the fixed-n step uses it. */
INLINE void theta_add_prod(canrls_theta64 *q, int32_t a, int32_t b, uint32_t *n)
{
    const int64_t t = (int64_t)(((uint64_t)(uint32_t)q->word << 32) | q->frac);
    const int64_t u = mul_ww(a, b);
    int64_t x;
    if (UNLIKELY(__builtin_add_overflow(t, u, &x))) {
        *n += 1u;
        q->frac = u > 0 ? 0xFFFFFFFFu : 0u;
        q->word = u > 0 ? INT32_MAX : INT32_MIN;
        return;
    }
    q->frac = (uint32_t)x;
    q->word = (int32_t)(x >> 32);
}
#endif

/* The 64-bit P (canrls_P64: word and lo, the pair X = V + 2^31 with V = P~ 2^32) minus
 * u = whole 2^32 + part (0 <= part < 2^32), saturated: X clamped to [lo 2^32,
 * hi 2^32 + 2^32 - 1], i.e. the word to [lo, hi] (counted). The general case (Python
 * reference_block: V <- V - u, any shift, any P word). */
INLINE void P_sub(canrls_P64 *q, int64_t whole, uint32_t part, int32_t lo, int32_t hi,
                  uint32_t *n)
{
    const uint32_t l = q->lo - part; /* mod 2^32, borrow when q->lo < part */
    const int64_t w = (int64_t)q->word - whole - (int64_t)(q->lo < part);
    if (UNLIKELY(w > hi)) {
        *n += 1u;
        q->lo = 0xFFFFFFFFu;
        q->word = hi;
        return;
    }
    if (UNLIKELY(w < lo)) {
        *n += 1u;
        q->lo = 0u;
        q->word = lo;
        return;
    }
    q->lo = l;
    q->word = (int32_t)w;
}

/* P_sub for the common case: 33 <= s <= 62 and the whole int32_t word, u = ph 2^(64-s)
 * with ph the rounded high word of K_i h_j, -u = ph nm (nm = neg_pow2(s): one SMULL): the
 * pair as one int64_t plus ph nm, saturated where the 64-bit sum overflows, which is
 * exactly where the word leaves the int32_t (as theta_add_full). */
INLINE void P_sub_full(canrls_P64 *q, int32_t ph, int32_t nm, int32_t s, uint32_t *n)
{
#if defined(__GNUC__)
    const int64_t t = (int64_t)(((uint64_t)(uint32_t)q->word << 32) | q->lo);
    int64_t x;
    if (UNLIKELY(__builtin_add_overflow(t, mul_ww(ph, nm), &x))) {
        *n += 1u;
        q->lo = ph < 0 ? 0xFFFFFFFFu : 0u;
        q->word = ph < 0 ? INT32_MAX : INT32_MIN;
        return;
    }
    (void)s;
    q->lo = (uint32_t)x;
    q->word = (int32_t)(x >> 32);
#else
    (void)nm;
    P_sub(q, ph >> (s - 32), (uint32_t)ph << (64 - s), INT32_MIN, INT32_MAX, n);
#endif
}

/* The 64-bit P from a word w (any int64_t) and a pair's low part t (0 <= t < 2^32 + 2^31:
 * the fraction plus 2^31, carry included), saturated as P_sub. */
SMALL_NOINLINE void P_put(canrls_P64 *q, int64_t w, uint64_t t, int32_t lo, int32_t hi, uint32_t *n)
{
    w += (int64_t)(t >> 32);
    if (w > hi) {
        *n += 1u;
        q->lo = 0xFFFFFFFFu;
        q->word = hi;
    } else if (w < lo) {
        *n += 1u;
        q->lo = 0u;
        q->word = lo;
    } else {
        q->lo = (uint32_t)t;
        q->word = (int32_t)w;
    }
}

/* V <- rsh(V c, c_s), 0 < c, 1 <= c_s <= 31: the fold of c into P~ (rare: e = 0).
 * V c + 2^(c_s-1) = A2 2^32 + Bl exactly (A = word c, B = f c + 2^(c_s-1), f the
 * fraction), and rsh(V c, c_s) = (A2 >> c_s) 2^32 + T with 0 <= T < 2^32. */
static void P_fold(canrls_P64 *q, int32_t c, int32_t c_s, int32_t lo, int32_t hi, uint32_t *n)
{
    const int32_t f = (int32_t)(q->lo ^ 0x80000000u);
    const int64_t B = (int64_t)f * c + ((int64_t)1 << (c_s - 1));
    const int64_t A2 = (int64_t)q->word * c + (B >> 32);
    const uint32_t T = ((uint32_t)A2 << (32 - c_s)) | ((uint32_t)B >> c_s);
    /* the pair: + 2^31 */
    P_put(q, A2 >> c_s, (uint64_t)T + 0x80000000u, lo, hi, n);
}

/* V <- V 2^sh, 1 <= sh <= 31, exactly (the block exponent's shift; rare):
 * word 2^sh plus the carry of f 2^sh + 2^31 (f the fraction) */
static void P_shift(canrls_P64 *q, int32_t sh, int32_t lo, int32_t hi, uint32_t *n)
{
    const int32_t f = (int32_t)(q->lo ^ 0x80000000u);
    const int64_t t = (int64_t)f * ((int64_t)1 << sh) + ((int64_t)1 << 31);
    const int64_t w = (int64_t)q->word * ((int64_t)1 << sh) + (t >> 32);
    P_put(q, w, (uint32_t)t, lo, hi, n);
}

/* Store an accumulator x (scale 2^-(f+s)) into a word of scale 2^-f (Python store):
 * s >= 0: rounding right shift then clamp; s < 0: a left shift that clamps before
 * shifting, so it never wraps. */
INLINE int32_t store(int64_t x, int32_t s, int32_t lo, int32_t hi, uint32_t *n)
{
    int32_t t;
    if (LIKELY((uint32_t)(s - 1) < 31u)) {
        /* 1 <= s <= 31 (the common case): x + 2^(s-1) shifted as two words */
        const uint64_t u = (uint64_t)x + (uint32_t)((uint32_t)1 << (s - 1)); /* s <= 31 */
        const uint32_t ulo = (uint32_t)u;
        const int32_t uhi = (int32_t)(uint32_t)(u >> 32);
        return sat2(uhi >> s, (ulo >> s) | ((uint32_t)uhi << (32 - s)), lo, hi, n);
    }
    if (s >= 0) {
        return sat(rsh_c(x, s, shift_class(s)), lo, hi, n);
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

/* Number of leading zero bits of v != 0. */
static inline int32_t nlz(uint32_t v)
{
#if defined(__GNUC__)
    return (int32_t)__builtin_clz(v);
#else
    int32_t k = 0;
    while ((v & 0x80000000u) == 0u) {
        v <<= 1;
        k += 1;
    }
    return k;
#endif
}

/* The left shift that brings 0 <= m < 2^31 to 30 bits: 30 - bit_length(m), at least 0
 * (30 for m = 0); x << norm_shift(m) lies in [-2^30, 2^30) for every |x| "<=" m. */
static inline int32_t norm_shift(uint32_t m)
{
    const int32_t k = m == 0u ? 30 : nlz(m) - 2;
    return k > 0 ? k : 0;
}

/* One 16-bit digit of a long division: num / (vn1 b + vn0) with b = 2^16, ``next`` the
 * next 16-bit digit of the dividend; the estimate num / vn1 corrected (at most twice). */
SMALL_NOINLINE uint32_t div_digit(uint32_t num, uint32_t next, uint32_t vn1, uint32_t vn0)
{
    const uint32_t b = 65536u;
    uint32_t q = num / vn1;
    uint32_t rhat = num - q * vn1;
    while (q >= b || q * vn0 > b * rhat + next) {
        q -= 1u;
        rhat += vn1;
        if (rhat >= b) {
            break;
        }
    }
    return q;
}

/* u / v truncated, for u < 2^32 v (the quotient fits 32 bits) and v > 0: two 32/32
 * divisions on 16-bit digits of the normalised operands (Knuth's algorithm D as in
 * Hacker's Delight, divlu), exact, instead of a 64/64 library division. */
static uint32_t div_u64_u32(uint64_t u, uint32_t v)
{
    const int32_t s = nlz(v);
    const uint32_t u1 = (uint32_t)(u >> 32), u0 = (uint32_t)u;
    uint32_t vn1, vn0, un32, un21, un10, un1, un0, q1, q0;
    v <<= s;
    vn1 = v >> 16;
    vn0 = v & 0xFFFFu;
    un32 = s > 0 ? (u1 << s) | (u0 >> (32 - s)) : u1;
    un10 = u0 << s;
    un1 = un10 >> 16;
    un0 = un10 & 0xFFFFu;
    /* first digit, the remainder, second digit */
    q1 = div_digit(un32, un1, vn1, vn0);
    un21 = un32 * 65536u + un1 - q1 * v;
    q0 = div_digit(un21, un0, vn1, vn0);
    return q1 * 65536u + q0;
}

/* ------------------------------------------------------------------- set-up */

/* bits of canrls_rls_q31.wide: the word is the whole int32_t (nothing to clamp) */
enum { WIDE_PHI = 1, WIDE_H = 2, WIDE_THETA = 4, WIDE_P = 8 };

INLINE uint32_t wide_bit(int32_t lo, int32_t hi, uint32_t bit)
{
    return lo == INT32_MIN && hi == INT32_MAX ? bit : 0u;
}

/* canrls_rls_q31.wide of a plan */
INLINE uint32_t plan_wide(const canrls_plan_q31 *plan)
{
    return wide_bit(plan->phi_lo, plan->phi_hi, WIDE_PHI)
           | wide_bit(plan->h_lo, plan->h_hi, WIDE_H)
           | wide_bit(plan->theta_lo, plan->theta_hi, WIDE_THETA)
           | wide_bit(plan->P_lo, plan->P_hi, WIDE_P);
}

/* the wide bits of the step: constants with the constant plan */
#if PLAN_IS_CONST
#define WIDE(S) plan_wide(&plan_const)
#else
#define WIDE(S) ((S)->wide)
#endif

#if PLAN_IS_CONST
/* a plan other than the constant one (trace_max_lam, which the target moves, aside) */
static int plan_differs(const canrls_plan_q31 *plan)
{
    return 0
#define CANRLS_PLAN_DIFFERS(f)                                                             \
    || (offsetof(canrls_plan_q31, f) != offsetof(canrls_plan_q31, trace_max_lam)           \
        && plan->f != plan_const.f)
        CANRLS_PLAN_FIELDS(CANRLS_PLAN_DIFFERS)
#undef CANRLS_PLAN_DIFFERS
        ;
}
#endif

/* trw = sum_i rsh(Pw_ii, trace_ps): the trace at the windup test's scale */
static int32_t trace_words(const canrls_rls_q31 *S)
{
    const canrls_P64 *Pii = S->P;
    int64_t trw = 0;
    uint32_t i;
    for (i = 0; i < S->n; i++) {
        trw += rsh32(Pii->word, PLAN(S)->trace_ps);
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
#ifdef CANRLS_N
    if (n != (uint32_t)CANRLS_N) {
        return CANRLS_EINVAL;
    }
#endif
#if PLAN_IS_CONST
    if (plan_differs(plan)) {
        return CANRLS_EINVAL;
    }
#endif
    for (i = 0; i < n; i++) {
        if (p0[i] < plan->P_lo || p0[i] > plan->P_hi) {
            return CANRLS_EINVAL;
        }
    }
    canrls_fill(S, 0u, sizeof *S);
    S->plan = plan;
    S->n = n;
    /* P0 = diag(p0) 2^-(f_P + e0), c = 1, the fractions 0 (lo = 2^31) ; theta0 = 0 with
     * fraction 0 (the memset) */
    for (i = 0; i < CANRLS_TRI(n); i++) {
        S->P[i].lo = 0x80000000u;
    }
    for (i = 0; i < n; i++) {
        S->P[canrls_tri_index(n, i, i)].word = p0[i];
    }
    S->e = e0;
    S->c = plan->one_lam;
    S->trw = trace_words(S);
    /* the e for which the windup test runs: trace_max_lim >> e is monotonic in e, so
     * they form an interval (empty: wu_lo > wu_hi) */
    S->wu_lo = plan->e_max + 1;
    S->wu_hi = -1;
    for (i = 0; i <= (uint32_t)plan->e_max; i++) {
        if (plan->trace_max_lam <= (plan->trace_max_lim >> i)) {
            S->wu_lo = S->wu_lo < (int32_t)i ? S->wu_lo : (int32_t)i;
            S->wu_hi = (int32_t)i;
        }
    }
    S->wide = plan_wide(plan);
    return CANRLS_OK;
}

int canrls_restore_q31(canrls_rls_q31 *S, const int32_t *theta, const uint32_t *theta_frac,
                       const int32_t *P_up, const int32_t *P_frac_up, int32_t e, int32_t c)
{
    const canrls_plan_q31 *p;
    uint32_t i, m;
    if (S == NULL || S->plan == NULL || theta == NULL || P_up == NULL) {
        return CANRLS_EINVAL;
    }
    p = PLAN(S);
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
    /* theta_q: the word theta and the fraction below its LSB theta_frac (NULL: 0, the
     * estimate at its word) */
    for (i = 0; i < S->n; i++) {
        S->theta_q[i].word = theta[i];
        S->theta_q[i].frac = theta_frac != NULL ? theta_frac[i] : 0u;
    }
    /* P: the word and its fraction (NULL: 0), the fraction held + 2^31 */
    for (i = 0; i < m; i++) {
        S->P[i].word = P_up[i];
        S->P[i].lo = (uint32_t)(P_frac_up != NULL ? P_frac_up[i] : 0) ^ 0x80000000u;
    }
    S->e = e;
    S->c = c;
    S->trw = trace_words(S);
    return CANRLS_OK;
}

/* ------------------------------------------------------------------- kernel */

/* sum_i rsh(h_i w_i, vw_ps) with h_i = w_i = rsh(h~_i c, hc_s) (the windup test's
 * h'w): h_i^2 one SMULL where h_i is a word; ``cls`` (a constant at each call):
 * SHIFT_LOW where both shifts are 1..31 (two-word shifts), else SHIFT_ANY. */
INLINE int64_t windup_vw(const int32_t *h, uint32_t n, int32_t c, int32_t hc_s, int32_t vw_ps,
                         int cls)
{
    int64_t a_vw = 0;
    uint32_t i;
    for (i = 0; i < n; i++) {
        const int64_t hi_ = rsh_c(mul_ww(h[i], c), hc_s, cls);
        const int64_t hw = (int64_t)(int32_t)hi_ == hi_
                               ? mul_ww((int32_t)hi_, (int32_t)hi_) : hi_ * hi_;
        a_vw += rsh_c(hw, vw_ps, cls);
    }
    return a_vw;
}

/* windup_vw where c = 2^k, k <= hc_s (the forgetting scale at its one, as after
 * canrls_init_q31, and with lambda = 1 always): h_i = rsh(h~_i 2^k, hc_s) = rsh(h~_i, s),
 * s = hc_s - k, a shift of the word; then h_i^2 (one SMULL) rounded by 1 <= vw_ps <= 31
 * bits on two words (h_i^2 >= 0). The same integers. */
INLINE int64_t windup_vw_pow2(const int32_t *h, uint32_t n, int32_t s, int32_t vw_ps)
{
    const int32_t t0 = s > 0, t1 = s - t0; /* rsh(x, s) = ((x >> t1) + t0) >> t0 */
    const uint32_t half = (uint32_t)1 << (vw_ps - 1);
    uint64_t a_vw = 0;
    uint32_t i;
    UNROLL
    for (i = 0; i < n; i++) {
        const int32_t hi_ = ((h[i] >> t1) + t0) >> t0;
        const uint64_t u = (uint64_t)mul_ww(hi_, hi_) + half;
        const uint32_t ulo = (uint32_t)u, uhi = (uint32_t)(u >> 32);
        a_vw += ((uint64_t)(uhi >> vw_ps) << 32) | ((ulo >> vw_ps) | (uhi << (32 - vw_ps)));
    }
    return (int64_t)a_vw;
}

/* A = sum_i h_i^2 with h_i = rsh(h~_i, s), one SMLAL an element (s = 0, ``s0`` a
 * constant at each call: h_i = h~_i), and the OR of |h_i| (one's complement) in *mm: A is
 * exact where *mm < 2^29 and n < 64 (each term at most 2^58) */
INLINE uint64_t windup_sq(const int32_t *h, uint32_t n, int32_t s, int s0, uint32_t *mm)
{
    const int32_t t0 = s > 0, t1 = s - t0; /* rsh(x, s) = ((x >> t1) + t0) >> t0 */
    uint64_t a = 0;
    uint32_t i, o = 0;
    UNROLL
    for (i = 0; i < n; i++) {
        const int32_t hi_ = s0 ? h[i] : ((h[i] >> t1) + t0) >> t0;
        o |= (uint32_t)(hi_ ^ (hi_ >> 31));
        a = mla_ww(a, hi_, hi_);
    }
    *mm = o;
    return a;
}

/* the windup test's comparison of its two sides, lhs and a_vw, whose scales differ by
 * df bits (non-increasing in a_vw) */
static inline int windup_cmp(int64_t lhs, int64_t a_vw, int32_t df)
{
    if (df >= 0) {
        return (lhs >> (df < 63 ? df : 63)) > a_vw;
    }
    return lhs > (a_vw >> (-df < 63 ? -df : 63));
}

/* The windup test once T = tr P - lambda trace_max > 0 (rare: while P falls from the
 * prior), out of line: (tr P - lambda trace_max) (lambda + phi'P phi) > h'h, the two
 * sides at their scales (docs/fixed_point.md) */
RARE int windup_up(const canrls_rls_q31 *S, int64_t T, int32_t sv)
{
    /* the plan, h~, c and e of the step (c and e not yet moved) */
    const canrls_plan_q31 *p = PLAN(S);
    const int32_t *h = S->h;
    const uint32_t n = NPAR(S);
    const int32_t c = S->c, e = S->e;
    uint32_t none = 0; /* d_lam is not counted */
    const int32_t d_lam = sat((int64_t)p->lam_den + sv, p->den_lo, p->den_hi, &none);
    /* 0 < min(T, P_hi) <= P_hi: a word, one SMULL */
    const int64_t lhs = rsh_w(mul_ww((int32_t)(T < p->P_hi ? T : p->P_hi), d_lam), p->lhs_ps);
    /* the two sides differ in scale by cmp_df - e bits */
    const int32_t df = p->cmp_scale_diff - e;
    int64_t a_vw;
    /* h = c h~ ; w = c w~ = h:  a_vw = sum_i rsh(h_i w_i, vw_ps) */
    if (!CANRLS_SMALL && (c & (c - 1)) == 0 && 31 - nlz((uint32_t)c) <= p->hc_s
        && (uint32_t)(p->vw_ps - 1) < 31u) {
        const int32_t s = p->hc_s - (31 - nlz((uint32_t)c));
        uint32_t mm;
        const uint64_t A = s == 0 ? windup_sq(h, n, 0, 1, &mm) : windup_sq(h, n, s, 0, &mm);
        const uint64_t An = A + ((uint64_t)n << (p->vw_ps - 1));
        if ((mm >> 29) == 0u && n < 64u) {
            /* A = sum_i h_i^2 exact: the rounded terms' sum a_vw lies in [Q - (n - 1), Q],
             * Q = floor((A + n 2^(vw_ps - 1)) / 2^vw_ps) (a sum of n floors is within
             * n - 1 of the floor of the sum): the test is decided by these bounds unless
             * lhs falls between them */
            const int64_t Q = (int64_t)(An >> p->vw_ps);
            if (df >= 0) {
                const int64_t L = lhs >> (df < 63 ? df : 63);
                if (L > Q || L <= Q - (int64_t)(n - 1u)) {
                    return L > Q;
                }
            } else {
                /* the other side shifted by r = -df: (Q - (n - 1)) >> r is at least
                 * (Q >> r) - (n - 1), a lower bound enough to decide */
                const int64_t Qs = Q >> (-df < 63 ? -df : 63);
                if (lhs > Qs || lhs <= Qs - (int64_t)(n - 1u)) {
                    return lhs > Qs;
                }
            }
        }
        a_vw = windup_vw_pow2(h, n, s, p->vw_ps);
    } else if ((uint32_t)(p->hc_s - 1) < 31u && (uint32_t)(p->vw_ps - 1) < 31u) {
        a_vw = windup_vw(h, n, c, p->hc_s, p->vw_ps, SHIFT_LOW);
    } else {
        a_vw = windup_vw(h, n, c, p->hc_s, p->vw_ps, SHIFT_ANY);
    }
    return windup_cmp(lhs, a_vw, df);
}

/* h~_i from its sum u = acc_i + 2^(h_os-1) (the rounding half already added), for
 * 1 <= h_os <= 31: u >> h_os fits a word iff the high word of u lies in
 * [-2^(h_os-1), 2^(h_os-1)); then it is the two words shifted. ``full``: the h word is
 * the whole int32_t (a constant at each call). */
INLINE int32_t h_word(uint64_t u, int32_t h_os, int32_t lo, int32_t hi, uint32_t *c_h,
                      int full)
{
    const uint32_t ulo = (uint32_t)u;
    const int32_t uhi = (int32_t)(uint32_t)(u >> 32);
    if (LIKELY((uint32_t)uhi + ((uint32_t)1 << (h_os - 1)) < ((uint32_t)1 << h_os))) {
        const int32_t r = (int32_t)((ulo >> h_os) | ((uint32_t)uhi << (32 - h_os)));
        return full ? r : clamp32(r, lo, hi, c_h);
    }
    *c_h += 1u;
    return uhi < 0 ? lo : hi;
}

/* acc = P~ phi + rnd as exact 64-bit sums (the rounding half rnd of the store of h~
 * added once to each). Symmetric: each P~_ij of the packed upper triangle read once;
 * its two products go to h_i and, scattered, to h_j. */
INLINE void h_sums(const canrls_P64 *Pr, const int32_t *phg, uint32_t n, int64_t rnd,
                   int64_t *acc)
{
    uint32_t i, j;
    for (i = 0; i < n; i++) {
        const int32_t pi_ = phg[i];
        /* h_i = sum_{j<i} P_ji phi_j (scattered by the rows above) + P_ii phi_i (the words) */
        int64_t a = (i == 0 ? rnd : acc[i]) + (int64_t)Pr[0].word * pi_;
        if (i == 0) {
            for (j = 1; j < n; j++) {
                const int32_t Pij = Pr[j].word;
                /* P_0j phi_j -> h_0 ;  P_j0 phi_0 = P_0j phi_0 -> h_j */
                a += (int64_t)Pij * phg[j];
                acc[j] = rnd + (int64_t)Pij * pi_;
            }
        } else {
            for (j = i + 1; j < n; j++) {
                const int32_t Pij = Pr[j - i].word;
                /* P_ij phi_j -> h_i ;  P_ji phi_i = P_ij phi_i -> h_j */
                a += (int64_t)Pij * phg[j];
                acc[j] += (int64_t)Pij * pi_;
            }
        }
        acc[i] = a;
        Pr += n - i;
    }
}

#if CANRLS_FAST
/* n a constant (CANRLS_N): h~ = P~ phi row by row, each P~_ij at a constant index of
 * the packed upper triangle (the same exact sums as h_sums), stored as it is summed;
 * returns s~ = phi' h~ and m = OR of |h~_i| (one's complement). 1 <= h_os <= 31. */
INLINE int64_t h_rows(const canrls_P64 *Pr, const int32_t *phg, int32_t *h, int32_t h_os,
                      int32_t lo, int32_t hi, uint32_t *c_h, uint32_t *m, int full)
{
    const uint32_t n = CANRLS_N;
    const int64_t rnd = (int64_t)((uint32_t)1 << (h_os - 1)); /* h_os <= 31: one word */
    int64_t s = 0;
    uint32_t i, j, mm = 0;
    int32_t ph[CANRLS_N]; /* phi >> phi_ps, held in registers over the rows */
    UNROLL
    for (j = 0; j < n; j++) {
        ph[j] = phg[j];
    }
    UNROLL
    for (i = 0; i < n; i++) {
        int64_t a = rnd;
        int32_t hi_;
        UNROLL
        for (j = 0; j < n; j++) {
            const uint32_t r = i < j ? i : j, q = i < j ? j : i;
            /* h~_i = sum_j Pw_ij phi_j   (Pw_ij = Pw_ji: the upper triangle's words) */
            a += (int64_t)Pr[r * n - r * (r - 1u) / 2u + (q - r)].word * ph[j];
        }
        hi_ = h_word((uint64_t)a, h_os, lo, hi, c_h, full);
        h[i] = hi_;
        mm |= (uint32_t)(hi_ ^ (hi_ >> 31));
    }
    UNROLL
    for (i = 0; i < n; i++) {
        /* s~ = phi' h~ */
        s += (int64_t)ph[i] * h[i];
    }
    *m = mm;
    return s;
}

/* the two instances, out of line: each loop gets the registers to itself */
NOINLINE int64_t h_rows_full(const canrls_P64 *Pr, const int32_t *phg, int32_t *h,
                             int32_t h_os, uint32_t *c_h, uint32_t *m)
{
    return h_rows(Pr, phg, h, h_os, INT32_MIN, INT32_MAX, c_h, m, 1);
}

NOINLINE int64_t h_rows_word(const canrls_P64 *Pr, const int32_t *phg, int32_t *h,
                             int32_t h_os, int32_t lo, int32_t hi, uint32_t *c_h, uint32_t *m)
{
    return h_rows(Pr, phg, h, h_os, lo, hi, c_h, m, 0);
}
#endif

/* h~ <- h~ 2^kn; K = (g c) h~ as the high word of (h~ 2^kn)(gc 2^g_up), rounded half up;
 * theta <- theta + K eps. ``cls`` (a constant at each call) is the shift class of th_s. */
INLINE void K_step(canrls_rls_q31 *S, int32_t kn, int32_t gcn, int32_t epn, int32_t th_s,
                   uint32_t *c_th, int cls, int full)
{
    const uint32_t n = NPAR(S);
    int32_t *const h = S->h;
    int32_t *const K = S->K;
    canrls_theta64 *const theta_q = S->theta_q;
    const int32_t th_lo = PLAN(S)->theta_lo, th_hi = PLAN(S)->theta_hi;
    /* -2^(64 - th_s): the high word of K eps at 2^-32 LSB (``full`` with SHIFT_HIGH: the
     * caller guarantees th_s >= 34 and the whole int32_t theta word) */
    const int32_t m = cls == SHIFT_HIGH && full ? neg_pow2(th_s) : 0;
    uint32_t i;
    for (i = 0; i < n; i++) {
        /* h~ <- h~ 2^kn (exact: the normalisation) */
        const int32_t hn = (int32_t)((uint32_t)h[i] << kn);
        /* K = P phi / (lambda + phi' P phi) = (g c) h~: the high word, rounded */
        const int32_t Ki = mul_rsh32(hn, gcn);
        h[i] = hn;
        K[i] = Ki;
        /* theta_q <- theta_q + K eps   (64 bits: K eps floored to 2^-32 LSB, so that
         * updates below the LSB accumulate; K carries the exponent e + kn: shifted out
         * here) */
        if (cls == SHIFT_HIGH && full) {
            theta_add_full(&theta_q[i], (int32_t)(mul_ww(Ki, epn) >> 32), m, th_s, c_th);
        } else {
            theta_add(&theta_q[i], (int64_t)Ki * epn, th_s, th_lo, th_hi, c_th);
        }
    }
}

/* P~ <- P~ - K h~'  (upper triangle, in 64 bits: V <- V - u). ``cls`` (a constant at each
 * call) is the shift class of P_s: SHIFT_HIGH and SHIFT_32 (P_s >= 32) take the product's
 * high word rounded half up, ph = rsh(K_i h~_j, 32), and u = ph 2^(64 - P_s) (``full``:
 * P_s >= 34 and the whole int32_t word, one SMULL by 2^(64 - P_s)); SHIFT_LOW and SHIFT_ANY
 * (P_s <= 31) u = K_i h~_j 2^(32 - P_s) exactly. Returns the low-excitation test of the
 * specification, "u_ii == 0 for every i": those are the diagonal terms of this update,
 * so they are tested here rather than computed twice. */
INLINE int P_step(canrls_rls_q31 *S, int32_t P_s, uint32_t *c_P, int cls, int full)
{
    const uint32_t n = NPAR(S);
    const int32_t *const h = S->h;
    const int32_t *const K = S->K;
    /* the plan, as locals (a store to P~ cannot change them) */
    const int32_t P_lo = PLAN(S)->P_lo, P_hi = PLAN(S)->P_hi;
    /* -2^(64 - P_s) (``full``), and the shifts of ph 2^(64 - P_s) as whole and part */
    const int32_t m = cls == SHIFT_HIGH && full ? neg_pow2(P_s) : 0;
    const int32_t hs = cls == SHIFT_HIGH ? P_s - 32 : 0;
    const int32_t ls = cls == SHIFT_HIGH ? 64 - P_s : 0;
    canrls_P64 *Pw = S->P; /* row i of the packed upper triangle */
    uint32_t i, j;
    uint32_t nz = 0; /* nonzero once a diagonal term is */
    for (i = 0; i < n; i++) {
        const int32_t Ki = K[i];
        for (j = i; j < n; j++) {
            if (cls == SHIFT_VAR && P_s >= 32) {
                /* u = ph 2^(64 - P_s), ph = rsh(K_i h~_j, 32) (P_s = 32: the word alone) */
                const int32_t ph = mul_rsh32(Ki, h[j]);
                if (j == i) {
                    nz |= (uint32_t)ph;
                }
                P_sub(&Pw[j - i], ph >> (P_s - 32), P_s > 32 ? (uint32_t)ph << (64 - P_s) : 0u,
                      P_lo, P_hi, c_P);
            } else if (cls == SHIFT_HIGH || cls == SHIFT_32) {
                /* ph = rsh(K_i h~_j, 32): the high word, rounded (one SMMULR) */
                const int32_t ph = mul_rsh32(Ki, h[j]);
                if (j == i) {
                    nz |= (uint32_t)ph; /* the diagonal: information K_i h~_i */
                }
                if (cls == SHIFT_32) {
                    /* u = ph 2^32: the word alone */
                    P_sub(&Pw[j - i], ph, 0u, P_lo, P_hi, c_P);
                } else if (full) {
                    P_sub_full(&Pw[j - i], ph, m, P_s, c_P);
                } else {
                    P_sub(&Pw[j - i], ph >> hs, (uint32_t)ph << ls, P_lo, P_hi, c_P);
                }
            } else {
                /* u = K_i h~_j 2^(32 - P_s): whole LSBs and the part below */
                const int64_t pr = (int64_t)Ki * h[j];
                if (j == i) {
                    nz |= (uint32_t)(pr != 0);
                }
                P_sub(&Pw[j - i], pr >> P_s, (uint32_t)((uint64_t)pr << (32 - P_s)), P_lo,
                      P_hi, c_P);
            }
        }
        Pw += n - i;
    }
    return nz == 0u;
}

/* the common instance of P_step (32-bit words, shifts of 34 or more), out of line: the
 * update of the triangle gets the registers to itself */
NOINLINE int P_step_high_full(canrls_rls_q31 *S, int32_t P_s, uint32_t *c_P)
{
    return P_step(S, P_s, c_P, SHIFT_HIGH, 1);
}

#if CANRLS_FAST

/* How the fixed-n step computes u, the decrement of V (P_step's shift classes, the same
 * integers): PM_HIGH  P_s >= 33: -u = ph nm, ph = rsh(K_i h~_j, 32), nm = neg_pow2(P_s);
 *          PM_32    P_s = 32: u = ph 2^32, the word alone;
 *          PM_LOW   P_s <= 31: u = K_i h~_j 2^(32 - P_s) exactly;
 *          PM_LOWK  the same as (K_i 2^a)(h~_j 2^b), a + b = 32 - P_s, both words (passed
 *                   as -(K_i 2^a), lowk_kword, and h~_j 2^b): -u = one product. */
enum { PM_HIGH = 0, PM_32 = 1, PM_LOW = 2, PM_LOWK = 3 };

/* How an element takes the block exponent's shift sh (a constant at each call): SH_NONE
 * sh = 0; SH_AFTER V - u, then (V - u) 2^sh; SH_FUSED (PM_HIGH, P_s >= 33 + sh) the same
 * with the pair's carried constant folded into the decrement, (ph + t) nm; SH_NEGK
 * (PM_LOWK, the K words passed negated) X - u as one SMLAL, X + (-K_i 2^a)(h~_j 2^b)
 * modulo 2^64. Each shifted form tests the room of V - u's high word, then shifts. */
enum { SH_NONE = 0, SH_AFTER = 1, SH_FUSED = 2, SH_NEGK = 3 };

/* The constants of a shift 1 <= sh <= 30: m2 = 2^sh; cp = 2^(31 - sh) - 2^31 = room cq,
 * cq = 2 - 2^(sh + 1), the pair's 2^31 carried through the shift
 * ((2^sh - 1) 2^31 = -cp 2^sh: X 2^sh - (2^sh - 1) 2^31 = (X + cp) 2^sh); room = 2^(30 - sh),
 * the bound of the high word below which V 2^sh stays in the pair; for SH_FUSED
 * t = (2^sh - 1) 2^(P_s - 33 - sh), t nm = cp. */
typedef struct {
    uint32_t m2, room;
    int32_t cq, t;
} P_shc;

INLINE P_shc shc_of(int32_t sh, int mode, int32_t P_s)
{
    P_shc k;
    k.m2 = (uint32_t)1 << sh;
    k.cq = (int32_t)(2u - (k.m2 << 1));
    k.room = (uint32_t)1 << (30 - sh);
    k.t = mode == PM_HIGH && P_s >= 33 + sh ? (int32_t)((k.m2 - 1u) << (P_s - 33 - sh)) : 0;
    return k;
}

/* acc - a 2^32 modulo 2^64: a subtracted from the high word (the pair one 64-bit
 * operand on Thumb-2, so that it stays where LDRD put it) */
INLINE uint64_t sub_hi(uint64_t acc, int32_t a)
{
#if defined(__GNUC__) && defined(__thumb2__)
    __asm__("sub %R0, %R0, %1" : "+r"(acc) : "r"(a));
    return acc;
#else
    return acc - ((uint64_t)(uint32_t)a << 32);
#endif
}

/* the pair of a canrls_P64 (X = V + 2^31) as one int64_t */
INLINE int64_t P_pair(const canrls_P64 *q)
{
    return (int64_t)(((uint64_t)(uint32_t)q->word << 32) | q->lo);
}

/* t + rsh(a b, 32) (one SMMLAR on a core with the DSP extension; no overflow where
 * the caller calls it) */
INLINE int32_t mul_rsh32_add(int32_t a, int32_t b, int32_t t)
{
#if defined(__GNUC__) && defined(__ARM_FEATURE_DSP) && defined(__thumb2__)
    int32_t r;
    __asm__("smmlar %0, %1, %2, %3" : "=r"(r) : "r"(a), "r"(b), "r"(t));
    return r;
#else
    return (int32_t)((uint32_t)t + (uint32_t)mul_rsh32(a, b));
#endif
}

/* X 2^sh modulo 2^64, X the pair (lo, hi), m2 = 2^sh: the low word times m2 (one UMULL)
 * plus the high word times m2 (one MLA). Written out on Thumb-2: GCC otherwise zeroes an
 * accumulator for UMLAL and moves it. */
INLINE uint64_t P_shl_sum(uint32_t lo, int32_t hi, uint32_t m2)
{
#if defined(__GNUC__) && defined(__thumb2__)
    uint32_t rl, rh;
    __asm__("umull %0, %1, %2, %4\n\t"
            "mla %1, %3, %4, %1"
            : "=&r"(rl), "=&r"(rh)
            : "r"(lo), "r"(hi), "r"(m2));
    return ((uint64_t)rh << 32) | rl;
#else
    return (uint64_t)lo * m2 + ((uint64_t)((uint32_t)hi * m2) << 32);
#endif
}

/* The exact general element, out of line (rare: a word that saturates, or a start-up
 * product too wide for the fast paths): V <- sat(V - u) as P_step, then V <- sat(V 2^sh)
 * as the block exponent's P_shift. Ki, hj as P_elem takes them. */
NOINLINE void P_elem_slow(canrls_P64 *q, int32_t Ki, int32_t hj, int mode, int32_t P_s,
                          int32_t sh, uint32_t *c_P)
{
    if (mode == PM_HIGH || mode == PM_32) {
        /* u = ph 2^(64 - P_s), ph = rsh(K_i h~_j, 32) */
        const int32_t ph = mul_rsh32(Ki, hj);
        if (P_s == 32) {
            P_sub(q, ph, 0u, INT32_MIN, INT32_MAX, c_P);
        } else {
            P_sub(q, ph >> (P_s - 32), (uint32_t)ph << (64 - P_s), INT32_MIN, INT32_MAX, c_P);
        }
    } else {
        /* u = K_i h~_j 2^(32 - P_s) (PM_LOWK: the product of the two shifted words) */
        const int64_t pr = mul_ww(Ki, hj);
        if (mode == PM_LOWK) {
            P_sub(q, pr >> 32, (uint32_t)pr, INT32_MIN, INT32_MAX, c_P);
        } else {
            P_sub(q, pr >> P_s, (uint32_t)((uint64_t)pr << (32 - P_s)), INT32_MIN, INT32_MAX,
                  c_P);
        }
    }
    if (sh > 0) {
        P_shift(q, sh, INT32_MIN, INT32_MAX, c_P);
    }
}

/* V <- V 2^sh, saturated, out of line (a word without room for the shift), from P_shl's D */
NOINLINE void P_shl_slow(canrls_P64 *q, uint64_t d, int32_t sh, uint32_t *c_P)
{
    /* the pair X = D - cp (modulo 2^64: exact) */
    const int64_t x = (int64_t)(d + (0x80000000u - ((uint32_t)1 << (31 - sh))));
    q->lo = (uint32_t)x;
    q->word = (int32_t)(x >> 32);
    P_shift(q, sh, INT32_MIN, INT32_MAX, c_P);
}

/* V <- V 2^sh exactly, in the pair x: X = V + 2^31 -> X 2^sh - (2^sh - 1) 2^31
 * = (X + cp) 2^sh, D = X + cp one SMLAL (room times cq), when D leaves room (the high word
 * within +-room: |D 2^sh| < 2^62; an X + cp below -2^63 wraps to a D that fails the
 * test). Else P_shift (saturated, counted). */
INLINE int32_t P_shl(canrls_P64 *q, int64_t x, int32_t sh, const P_shc *k, uint32_t *c_P)
{
    const uint64_t d = mla_ww((uint64_t)x, (int32_t)k->room, k->cq);
    const int32_t hi = (int32_t)(uint32_t)(d >> 32);
    if (LIKELY((uint32_t)(hi ^ (hi >> 31)) < k->room)) {
        const uint64_t y = P_shl_sum((uint32_t)d, hi, k->m2);
        q->lo = (uint32_t)y;
        q->word = (int32_t)(uint32_t)(y >> 32);
        return q->word;
    }
    P_shl_slow(q, d, sh, c_P);
    return q->word;
}

/* The pair x = V - u into q: then (SH_AFTER) V <- V 2^sh (P_shl) */
INLINE void P_put_x(canrls_P64 *q, int64_t x, int32_t sh, int how, const P_shc *k,
                    uint32_t *c_P)
{
    if (how == SH_AFTER) {
        (void)P_shl(q, x, sh, k, c_P);
        return;
    }
    q->lo = (uint32_t)x;
    q->word = (int32_t)(x >> 32);
}

/* One element of the fixed-n step (32-bit P words): V <- sat(V - u) and, sh > 0, then
 * V <- sat(V 2^sh), the block exponent's shift folded into the same pass over P (the
 * integers of P_step followed by P_shift); the fast paths below, anything else (a
 * saturation, a product too wide) in P_elem_slow. ``nz``: the diagonal's low-excitation
 * test (SH_NONE only). */
INLINE void P_elem(canrls_P64 *q, int32_t Ki, int32_t hj, int mode, int32_t nm, int32_t P_s,
                   int32_t sh, int how, const P_shc *k, uint32_t *c_P, uint32_t *nz)
{
#if defined(__GNUC__)
    int64_t x;
#endif
    if (how == SH_NEGK || how == SH_FUSED
        || (how == SH_AFTER && (mode == PM_HIGH || mode == PM_32))) {
        /* D = X - u + cp modulo 2^64, and (V - u) 2^sh in the pair is D 2^sh (P_shl):
         * -u = ph nm (PM_HIGH, |u| <= 2^60), u = ph 2^32 (PM_32, the high word alone,
         * |u| <= 2^61), -u = Ki hj (SH_NEGK: PM_LOWK with Ki = -(K_i 2^a), a word,
         * |u| <= 2^62), each one SMLAL or a subtraction, cp = room cq one SMLAL; SH_FUSED
         * (P_s >= 33 + sh) -u + cp = (ph + t) nm, ph + t one SMMLAR (|ph| <= 2^29,
         * t < 2^(P_s - 33) <= 2^29: a word), one SMLAL. With X in
         * [-2^63, 2^63), |u| <= 2^62 and -2^31 <= cp < 0, an X - u + cp outside int64
         * leaves D = X - u + cp -+ 2^64 with |D| >= 2^62 - 2^31: its high word fails the
         * room test (room <= 2^29). A D that passes is exact and within +-2^(62 - sh): no
         * saturation in V - u nor in its 2^sh. Else the general element (Ki negated back:
         * K_i 2^a is a word). */
        uint64_t d = (uint64_t)P_pair(q);
        int32_t hi;
        if (how == SH_FUSED) {
            d = mla_ww(d, mul_rsh32_add(Ki, hj, k->t), nm);
        } else {
            if (mode == PM_LOWK) {
                d = mla_ww(d, Ki, hj);
            } else if (mode == PM_32) {
                d = sub_hi(d, mul_rsh32(Ki, hj));
            } else {
                d = mla_ww(d, mul_rsh32(Ki, hj), nm);
            }
            d = mla_ww(d, (int32_t)k->room, k->cq);
        }
        hi = (int32_t)(uint32_t)(d >> 32);
        if (LIKELY((uint32_t)(hi ^ (hi >> 31)) < k->room)) {
            const uint64_t z = P_shl_sum((uint32_t)d, hi, k->m2);
            q->lo = (uint32_t)z;
            q->word = (int32_t)(uint32_t)(z >> 32);
            return;
        }
        P_elem_slow(q, mode == PM_LOWK ? (int32_t)(0u - (uint32_t)Ki) : Ki, hj, mode, P_s, sh,
                    c_P);
        return;
    }
#if defined(__GNUC__)
    if (mode == PM_32) {
        /* u = ph 2^32: the word alone, saturated where it overflows */
        const int32_t ph = mul_rsh32(Ki, hj);
        int32_t w;
        if (nz != NULL) {
            *nz |= (uint32_t)ph;
        }
        if (UNLIKELY(__builtin_sub_overflow(q->word, ph, &w))) {
            P_elem_slow(q, Ki, hj, mode, P_s, sh, c_P);
            return;
        }
        if (how == SH_AFTER) {
            (void)P_shl(q, (int64_t)(((uint64_t)(uint32_t)w << 32) | q->lo), sh, k, c_P);
            return;
        }
        q->word = w;
        return;
    }
    if (mode == PM_HIGH) {
        /* -u = ph nm */
        const int32_t ph = mul_rsh32(Ki, hj);
        if (nz != NULL) {
            *nz |= (uint32_t)ph;
        }
        if (UNLIKELY(__builtin_add_overflow(P_pair(q), mul_ww(ph, nm), &x))) {
            P_elem_slow(q, Ki, hj, mode, P_s, sh, c_P);
            return;
        }
    } else {
        int64_t u;
        if (mode == PM_LOWK) {
            /* -u = (-K_i 2^a)(h~_j 2^b): one exact product (Ki negated, lowk_kword) */
            const int64_t nu = mul_ww(Ki, hj);
            if (nz != NULL) {
                *nz |= (uint32_t)nu | (uint32_t)((uint64_t)nu >> 32);
            }
            if (UNLIKELY(__builtin_add_overflow(P_pair(q), nu, &x))) {
                P_elem_slow(q, (int32_t)(0u - (uint32_t)Ki), hj, mode, P_s, sh, c_P);
                return;
            }
            P_put_x(q, x, sh, how, k, c_P);
            return;
        } else {
            /* u = K_i h~_j 2^k2, k2 = 32 - P_s (1..31), shifted on two words where it
             * fits 64 bits (else in P_elem_slow) */
            const int64_t pr = mul_ww(Ki, hj);
            const int32_t k2 = 32 - P_s;
            const uint32_t plo = (uint32_t)pr;
            const int32_t phw = (int32_t)(pr >> 32);
            if (nz != NULL) {
                *nz |= (uint32_t)(pr != 0);
            }
            if (UNLIKELY((uint32_t)((phw >> (31 - k2)) + 1) > 1u)) {
                P_elem_slow(q, Ki, hj, mode, P_s, sh, c_P);
                return;
            }
            u = (int64_t)(((uint64_t)(((uint32_t)phw << k2) | (plo >> (32 - k2))) << 32)
                          | (uint32_t)(plo << k2));
        }
        if (UNLIKELY(__builtin_sub_overflow(P_pair(q), u, &x))) {
            P_elem_slow(q, Ki, hj, mode, P_s, sh, c_P);
            return;
        }
    }
    P_put_x(q, x, sh, how, k, c_P);
#else
    if (nz != NULL) {
        *nz |= mode == PM_HIGH || mode == PM_32 ? (uint32_t)mul_rsh32(Ki, hj)
                                                : (uint32_t)(mul_ww(Ki, hj) != 0);
    }
    (void)nm, (void)how, (void)k;
    P_elem_slow(q, mode == PM_LOWK ? (int32_t)(0u - (uint32_t)Ki) : Ki, hj, mode, P_s, sh, c_P);
#endif
}

/* trw's term of a diagonal word x: rsh(x, trace_ps) (the word for trace_ps <= 0) */
INLINE uint32_t trw_term(int32_t x, int32_t tr_ps)
{
    return (uint32_t)(tr_ps > 0 ? ((x >> (tr_ps - 1)) + 1) >> 1 : x);
}

/* The off-diagonal elements and, with a shift, the diagonal's shift (its elements
 * updated before this pass), its constants made here from sh: the shift class ``mode`` and
 * how the block exponent's shift sh is taken (``how``) are constants at each call.
 * ``unroll`` (a constant): one straight run, else a loop over the packed rows (the rare
 * classes: less code). Returns, with a shift, trw = sum_i rsh(P~_ii, tr_ps) of the
 * shifted diagonal (modulo 2^32), else 0. */
INLINE uint32_t P_off(canrls_P64 *P, const int32_t *K, const int32_t *hn, int mode, int32_t nm,
                      int32_t P_s, int32_t sh, int32_t tr_ps, int how, int unroll,
                      uint32_t *c_P)
{
    const uint32_t n = CANRLS_N;
    /* the constants as locals: the stores to P cannot change them */
    const P_shc k = how != SH_NONE ? shc_of(sh, mode, P_s) : shc_of(1, PM_LOW, 0);
    int32_t h[CANRLS_N]; /* h~ in a local array, likewise */
    canrls_P64 *Pw = P;
    uint32_t i, j, trw32 = 0;
    UNROLL
    for (j = 0; j < n; j++) {
        h[j] = hn[j];
    }
#define P_OFF_ROW                                                                          \
    /* (PM_LOWK: the K words come negated, lowk_kword) */                                 \
    const int32_t Ki = K[i];
    if (unroll) {
        UNROLL
        for (i = 0; i < n; i++) {
            P_OFF_ROW
            UNROLL
            for (j = i + 1; j < n; j++) {
                P_elem(&Pw[j - i], Ki, h[j], mode, nm, P_s, sh, how, &k, c_P, NULL);
            }
            Pw += n - i;
        }
    } else {
        for (i = 0; i < n; i++) {
            P_OFF_ROW
            for (j = i + 1; j < n; j++) {
                P_elem(&Pw[j - i], Ki, h[j], mode, nm, P_s, sh, how, &k, c_P, NULL);
            }
            Pw += n - i;
        }
    }
#undef P_OFF_ROW
    if (how != SH_NONE) {
        /* the diagonal (its elements updated before this pass) shifted, trw summed (the
         * rounding's 1 held in a register: 1 + (x >> (tr_ps - 1)) one ADD with a shifted
         * operand on Thumb-2) */
        int32_t one = 1;
        KEEP_REG(one);
        Pw = P;
        UNROLL
        for (i = 0; i < n; i++) {
            const int32_t x = P_shl(Pw, P_pair(Pw), sh, &k, c_P);
            trw32 += (uint32_t)(tr_ps > 0 ? (one + (x >> (tr_ps - 1))) >> 1 : x);
            Pw += n - i;
        }
    }
    return trw32;
}

/* each class of the step its own function: its registers and its stack frame to itself */
#define P_OFF_CLASS(name, mode_, how_, unroll_)                                           \
    NOINLINE uint32_t name(canrls_P64 *P, const int32_t *K, const int32_t *hn, int32_t nm,  \
                           int32_t P_s, int32_t sh, int32_t tr_ps, uint32_t *c_P)           \
    {                                                                                       \
        return P_off(P, K, hn, mode_, nm, P_s, how_ == SH_NONE ? 0 : sh, tr_ps, how_,       \
                     unroll_, c_P);                                                         \
    }
P_OFF_CLASS(P_off_high_fused, PM_HIGH, SH_FUSED, 1)
P_OFF_CLASS(P_off_high_after, PM_HIGH, SH_AFTER, 1)
P_OFF_CLASS(P_off_high, PM_HIGH, SH_NONE, 1)
P_OFF_CLASS(P_off_32_after, PM_32, SH_AFTER, 1)
P_OFF_CLASS(P_off_32, PM_32, SH_NONE, 1)
P_OFF_CLASS(P_off_lowk_neg, PM_LOWK, SH_NEGK, 1)
P_OFF_CLASS(P_off_lowk, PM_LOWK, SH_NONE, 1)
P_OFF_CLASS(P_off_low_after, PM_LOW, SH_AFTER, 0)
P_OFF_CLASS(P_off_low, PM_LOW, SH_NONE, 0)

/* The pass of the class (mode, sh > 0 or not); with a shift, returns the shifted
 * diagonal's trw (P_off), else 0 */
INLINE uint32_t P_off_any(canrls_P64 *P, const int32_t *K, const int32_t *hn, int mode,
                          int32_t nm, int32_t P_s, int32_t sh, int32_t tr_ps, uint32_t *c_P)
{
    /* one straight run for each class of the steady state and the start-up, with and
     * without the shift; a loop for the rest (rare) */
    if (mode == PM_HIGH && sh > 0 && P_s >= 33 + sh) {
        return P_off_high_fused(P, K, hn, nm, P_s, sh, tr_ps, c_P);
    } else if (mode == PM_HIGH && sh > 0) {
        return P_off_high_after(P, K, hn, nm, P_s, sh, tr_ps, c_P);
    } else if (mode == PM_HIGH) {
        return P_off_high(P, K, hn, nm, P_s, sh, tr_ps, c_P);
    } else if (mode == PM_32 && sh > 0) {
        return P_off_32_after(P, K, hn, nm, P_s, sh, tr_ps, c_P);
    } else if (mode == PM_32) {
        return P_off_32(P, K, hn, nm, P_s, sh, tr_ps, c_P);
    } else if (mode == PM_LOWK && sh > 0) {
        return P_off_lowk_neg(P, K, hn, nm, P_s, sh, tr_ps, c_P);
    } else if (mode == PM_LOWK) {
        return P_off_lowk(P, K, hn, nm, P_s, sh, tr_ps, c_P);
    } else if (sh > 0) {
        return P_off_low_after(P, K, hn, nm, P_s, sh, tr_ps, c_P);
    }
    return P_off_low(P, K, hn, nm, P_s, sh, tr_ps, c_P);
}

#if defined(__GNUC__)
/* theta_add at s = 32 and the whole int32_t word: the word plus ph, the high word of the
 * product (floor(p / 2^32) 2^32: the fraction unchanged), saturated where it overflows */
INLINE void theta_add_hi(canrls_theta64 *q, int32_t ph, uint32_t *n)
{
    int32_t w;
    if (UNLIKELY(__builtin_add_overflow(q->word, ph, &w))) {
        *n += 1u;
        q->frac = ph > 0 ? 0xFFFFFFFFu : 0u;
        q->word = ph > 0 ? INT32_MAX : INT32_MIN;
        return;
    }
    q->word = w;
}
#endif

/* The step after g and K at a fixed n (32-bit theta and P words): the diagonal of
 * P~ - K h~' first, so that c <- c / lambda_k and the block exponent's shift sh are known
 * before the rest of P is touched; then the off-diagonal elements with the shift folded
 * in (one pass over P: the shift's cost spread over the elements the update writes
 * anyway), the diagonal shifted, theta updated. The same integers as K_step, P_step, the
 * forgetting scale and the block exponent of canrls_update_q31 one after the other (the
 * order changes no integer: the theta and P updates read nothing the other writes, and
 * the shift of each element follows its own update). ``common`` (a constant at each
 * call): P_s >= 33 and th_s >= 33, the steady state, one straight run; ``mode`` (a
 * constant) the class of P_s: PM_HIGH, PM_32, PM_LOW or PM_LOWK (KP, hP: K 2^a, h~ 2^b;
 * else K, h~). A c to fold into
 * P~ (e = 0) is left to the caller (c > one_lam on return, no shift). Returns the
 * low-excitation test, as P_step. */
INLINE int KP_tail(canrls_rls_q31 *S, const int32_t *K, const int32_t *hn, const int32_t *KP,
                   const int32_t *hP, uint32_t mK, int32_t epn, int32_t th_s, int32_t P_s,
                   int32_t il, int32_t *e_io, int32_t *c_io, int32_t *trw_io, uint32_t *c_th,
                   uint32_t *c_P, int common, int mode)
{
    const uint32_t n = CANRLS_N;
    const canrls_plan_q31 *p = PLAN(S);
    const int32_t nm = mode == PM_HIGH ? neg_pow2(P_s) : 0;
    /* theta: th_s >= 33, the high word of K eps times 2^(64 - th_s) = -(ph nt) */
    const int32_t nt = common ? neg_pow2(th_s) : 0;
    const int32_t tr_ps = p->trace_ps;
    canrls_P64 *const P = S->P;
    canrls_P64 *Pw;
    const P_shc k0 = {0u, 0u, 0, 0}; /* (no shift) */
    /* e and c: the steady step reads them here, the others after the diagonal (GCC had
     * kept them on the stack across it) */
    int32_t e = common ? *e_io : 0, c = common ? *c_io : 0, sh = 0;
    int64_t tr = 0;
    uint32_t i, j, nz = 0, trw32 = 0;
    /* the diagonal: P~_ii <- P~_ii - K_i h~_i (the information K_i h~_i: low excitation) */
    Pw = P;
    UNROLL
    for (i = 0; i < n; i++) {
        P_elem(Pw, KP[i], hP[i], mode, nm, P_s, 0, SH_NONE, &k0, c_P, &nz);
        tr += Pw->word;
        if (mode == PM_LOWK) {
            KEEP_REG(tr); /* summed here (GCC had kept each word on the stack for it) */
        }
        Pw += n - i;
    }
    if (!common) {
        e = *e_io;
        c = *c_io;
    }
    /* c <- c / lambda_k ; c > 1 and e > 0: c/2 and 2^-e x 2 (the words do not move) */
    c = store(mul_ww(c, il), p->c_s, 0, p->lam_hi, c_P);
    if (c > p->one_lam && e > 0) {
        c = rsh32(c, 1);
        e -= 1;
    }
    /* block exponent: tr P~ fell to tr_hi/2 or below -> shift left by sh, e += sh (not
     * with a c to fold: the caller folds, then shifts) */
    if (UNLIKELY(c <= p->one_lam && tr > 0 && tr <= (p->trace_hi >> 1) && e < p->e_max)) {
        /* the largest sh with tr 2^sh <= tr_hi (at least 1 here) and e + sh <= e_max (tr
         * and tr 2^sh below 2^31 here: words) */
        const uint32_t t = (uint32_t)tr;
        sh = nlz(t) - nlz((uint32_t)p->trace_hi);
        if ((t << sh) > (uint32_t)p->trace_hi) {
            sh -= 1;
        }
        sh = sh < p->e_max - e ? sh : p->e_max - e;
    }
    /* the rest of P~ <- (P~ - K h~') 2^sh, the diagonal's 2^sh */
    if (common && LIKELY(sh == 0)) {
        Pw = P;
        UNROLL
        for (i = 0; i < n; i++) {
            UNROLL
            for (j = i + 1; j < n; j++) {
                /* -u = rsh(K_i h~_j, 32) nm */
                P_sub_full(&Pw[j - i], mul_rsh32(K[i], hn[j]), nm, P_s, c_P);
            }
            Pw += n - i;
        }
    } else {
        /* (with a shift, the pass sums trw) */
        trw32 = P_off_any(P, KP, hP, mode, nm, P_s, sh, tr_ps, c_P);
    }
    if (sh == 0) {
        /* trw = sum_i rsh(Pw_ii, trace_ps) (modulo 2^32: a word) */
        Pw = P;
        UNROLL
        for (i = 0; i < n; i++) {
            trw32 += trw_term(Pw->word, tr_ps);
            Pw += n - i;
        }
    }
    UNROLL
    for (i = 0; i < n; i++) {
        /* theta_q <- theta_q + K eps   (64 bits: K eps floored to 2^-32 LSB; K carries
         * the exponent e + kn: shifted out here; one LDRD, one STRD) */
        if (common || th_s >= 33) {
            theta_add_full(&S->theta_q[i], (int32_t)(mul_ww(K[i], epn) >> 32),
                           common ? nt : neg_pow2(th_s), th_s, c_th);
#if defined(__GNUC__)
        } else if (th_s == 32) {
            theta_add_hi(&S->theta_q[i], (int32_t)(mul_ww(K[i], epn) >> 32), c_th);
        } else if (th_s <= 31 && th_s >= 1 && (mK >> (th_s - 1)) == 0u) {
            /* K eps 2^(32 - th_s) exactly: (K 2^(32 - th_s)) eps, one product */
            theta_add_prod(&S->theta_q[i], (int32_t)((uint32_t)K[i] << (32 - th_s)), epn, c_th);
#endif
        } else {
            theta_add(&S->theta_q[i], mul_ww(K[i], epn), th_s, INT32_MIN, INT32_MAX, c_th);
        }
    }
    *e_io = e + sh;
    *c_io = c;
    *trw_io = (int32_t)trw32;
    return nz == 0u;
}


/* the tail of a step with P_s <= 31 whose K 2^a or h~ 2^b is not a word (rare: the loop
 * of PM_LOW), out of line: the PM_LOWK instance keeps its registers to itself */
NOINLINE int KP_tail_low(canrls_rls_q31 *S, const int32_t *K, const int32_t *hn, uint32_t mK,
                         int32_t epn, int32_t th_s, int32_t P_s, int32_t il, int32_t *e_io,
                         int32_t *c_io, int32_t *trw_io, uint32_t *c_th, uint32_t *c_P)
{
    return KP_tail(S, K, hn, K, hn, mK, epn, th_s, P_s, il, e_io, c_io, trw_io, c_th, c_P, 0,
                   PM_LOW);
}

/* PM_LOWK's split u = K_i h~_j 2^(32 - P_s) = (K_i 2^a)(h~_j 2^b), a + b = 32 - P_s: the
 * largest a that keeps every K_i 2^a a word above -2^31, so that its negation is one too
 * (|K_i| < 2^(31 - a), mA the OR of |K_i|), the rest b on h~ where h~ 2^b stays a word (mh
 * the OR of |h~_i| in one's complement). Returns 0 where no split fits (the loop of
 * PM_LOW). */
INLINE int lowk_split(uint32_t mA, uint32_t mh, int32_t P_s, int32_t *a_out, int32_t *b_out)
{
    const int32_t a0 = nlz(mA | 1u) - 1; /* mA <= 2^31: a0 >= -1 */
    const int32_t a = a0 < 32 - P_s ? a0 : 32 - P_s, b = 32 - P_s - a;
    *a_out = a;
    *b_out = b;
    return a >= 0 && b <= 31 && (mh >> (31 - b)) == 0u;
}

/* PM_LOWK's K word: -(K_i 2^a), one MUL by -2^a (a word where lowk_split took a: the
 * pass and the diagonal add (-K_i 2^a)(h~_j 2^b), one SMLAL) */
INLINE int32_t lowk_kword(int32_t K, int32_t a)
{
    return (int32_t)((uint32_t)K * (0u - ((uint32_t)1 << a)));
}

/* K and h~ as the P update takes them, then KP_tail: K = (g c) h~ 2^kn and h~ 2^kn, or, for
 * P_s <= 31 where both words keep room, K 2^a and h~ 2^b (PM_LOWK: each class of the tail
 * its own straight run). ``mh`` (PM_LOW): OR of |h~_i 2^kn| (one's complement). */
INLINE int KP_core(canrls_rls_q31 *S, int32_t kn, int32_t gcn, int32_t epn, int32_t th_s,
                   int32_t P_s, int32_t il, int32_t *e_io, int32_t *c_io, int32_t *trw_io,
                   uint32_t *c_th, uint32_t *c_P, uint32_t mh, int common, int cls)
{
    const uint32_t n = CANRLS_N;
    int32_t hn[CANRLS_N], K[CANRLS_N];
    uint32_t mK = 0;
    uint32_t i;
    if (!common && cls == PM_LOW) {
        /* K into S->K alone (the tail's theta reads it there), K 2^a and h~ 2^b from
         * S->K and S->h: nothing else kept */
        int32_t Kk[CANRLS_N], hk[CANRLS_N];
        int32_t a, b;
        UNROLL
        for (i = 0; i < n; i++) {
            const int32_t Ki = mul_rsh32((int32_t)((uint32_t)S->h[i] << kn), gcn);
            S->K[i] = Ki;
            /* |K_i| (the theta step's test of mK holds with it: |K_i| >= one's complement) */
            mK |= (uint32_t)(Ki ^ (Ki >> 31)) - (uint32_t)(Ki >> 31);
        }
        MEM_BARRIER();
        if (lowk_split(mK, mh, P_s, &a, &b)) {
            /* h~ 2^(kn + b): kn + b <= 30 unless every h~_i is 0 (then any shift is) */
            const uint32_t sb = (uint32_t)(kn + b) & 31u;
            UNROLL
            for (i = 0; i < n; i++) {
                Kk[i] = lowk_kword(S->K[i], a);
                hk[i] = (int32_t)((uint32_t)S->h[i] << sb);
            }
            return KP_tail(S, S->K, hk, Kk, hk, mK, epn, th_s, P_s, il, e_io, c_io, trw_io,
                           c_th, c_P, 0, PM_LOWK);
        }
        UNROLL
        for (i = 0; i < n; i++) {
            hn[i] = (int32_t)((uint32_t)S->h[i] << kn);
        }
        return KP_tail_low(S, S->K, hn, mK, epn, th_s, P_s, il, e_io, c_io, trw_io, c_th, c_P);
    }
    UNROLL
    for (i = 0; i < n; i++) {
        /* h~ <- h~ 2^kn (exact: the normalisation) */
        hn[i] = (int32_t)((uint32_t)S->h[i] << kn);
        /* K = P phi / (lambda + phi' P phi) = (g c) h~: the high word, rounded */
        K[i] = mul_rsh32(hn[i], gcn);
        S->K[i] = K[i];
        mK |= (uint32_t)(K[i] ^ (K[i] >> 31));
    }
    return KP_tail(S, K, hn, K, hn, mK, epn, th_s, P_s, il, e_io, c_io, trw_io, c_th, c_P,
                   common, cls);
}

/* the instances, out of line: the steady state (P_s, th_s >= 33) and any other step by
 * the class of P_s (each its registers and its stack frame) */
#define KP_STEP(name, common_, cls_)                                                       \
    NOINLINE int name(canrls_rls_q31 *S, int32_t kn, int32_t gcn, int32_t epn, int32_t th_s, \
                      int32_t P_s, int32_t il, int32_t *e_io, int32_t *c_io, int32_t *trw_io, \
                      uint32_t *c_th, uint32_t *c_P)                                         \
    {                                                                                        \
        return KP_core(S, kn, gcn, epn, th_s, P_s, il, e_io, c_io, trw_io, c_th, c_P, 0u,    \
                       common_, cls_);                                                       \
    }
KP_STEP(KP_step_common, 1, PM_HIGH)
KP_STEP(KP_step_high, 0, PM_HIGH)
KP_STEP(KP_step_32, 0, PM_32)

/* P_s <= 31; mh = OR of |h~_i 2^kn| (one's complement: m 2^kn, the shift exact) */
NOINLINE int KP_step_low(canrls_rls_q31 *S, int32_t kn, int32_t gcn, int32_t epn, int32_t th_s,
                         int32_t P_s, int32_t il, int32_t *e_io, int32_t *c_io, int32_t *trw_io,
                         uint32_t *c_th, uint32_t *c_P, uint32_t mh)
{
    return KP_core(S, kn, gcn, epn, th_s, P_s, il, e_io, c_io, trw_io, c_th, c_P, mh, 0,
                   PM_LOW);
}

#endif

int canrls_update_q31(canrls_rls_q31 *S, const int32_t *phi, int32_t y,
                      canrls_step_q31 *step)
{
    const canrls_plan_q31 *p = PLAN(S);
    const uint32_t n = NPAR(S);
    const canrls_theta64 *const theta_q = S->theta_q;
    canrls_P64 *const P = S->P;
    int32_t *const h = S->h;
    int32_t *const K = S->K;
    int32_t *const phg = S->phg;
    int32_t e = S->e;
    int32_t c = S->c;
    int32_t trw = S->trw;
    /* per-step saturation counts, added to S->counts once per step */
    uint32_t c_phi = 0, c_y = 0, c_eps = 0, c_h = 0, c_den = 0, c_div = 0, c_th = 0,
             c_P = 0;
    uint32_t flag = 0;
    uint32_t i, j;
    /* the plan, as locals (stores to the state cannot change them) */
    const int32_t phi_lo = p->phi_lo, phi_hi = p->phi_hi, phi_ps = p->phi_ps;
    const int32_t h_lo = p->h_lo, h_hi = p->h_hi, h_os = p->h_os;
    const int32_t tr_ps = p->trace_ps;
    int32_t yk, eps;
    int64_t a;
    int applied = 0;

    /* phi, y <- sat(phi), sat(y)       inputs clamped to their words;
     * phi >> ps: the guard bits of the multiply-accumulates */
    if (!CANRLS_SMALL && phi_ps > 0 && (WIDE(S) & WIDE_PHI)) {
        /* 32-bit words: nothing to clamp */
        UNROLL
        for (j = 0; j < n; j++) {
            phg[j] = ((phi[j] >> (phi_ps - 1)) + 1) >> 1;
        }
    } else if (CANRLS_SMALL || phi_ps > 0) {
        /* (built for size: every case in this loop, rsh32 by 0 the word itself) */
        for (j = 0; j < n; j++) {
            const int32_t v = clamp32(phi[j], phi_lo, phi_hi, &c_phi);
            phg[j] = rsh32(v, phi_ps);
        }
    } else {
        for (j = 0; j < n; j++) {
            phg[j] = clamp32(phi[j], phi_lo, phi_hi, &c_phi);
        }
    }
    yk = clamp32(y, p->y_lo, p->y_hi, &c_y);

    /* eps = y - phi' theta */
    /* (summed as phi' theta - y, multiply-accumulates, then negated: the same integer) */
    if (!CANRLS_SMALL && (uint32_t)p->eps_ts <= 30u) {
        a = (int64_t)yk * ((int32_t)1 << p->eps_ts); /* y 2^ts: one multiply */
    } else {
        a = p->eps_ts >= 0 ? (int64_t)yk * ((int64_t)1 << p->eps_ts) : rsh(yk, -p->eps_ts);
    }
    a = -a;
    UNROLL
    for (j = 0; j < n; j++) {
        a += (int64_t)phg[j] * theta_q[j].word;
    }
    a = -a;
    eps = store(a, p->eps_os, p->eps_lo, p->eps_hi, &c_eps);

    if (S->frozen) {
        flag = CANRLS_FLAG_FROZEN;
        canrls_fill(K, 0u, n * sizeof *K);
    } else {
        int64_t acc[CANRLS_N_MAX]; /* the scattered column sums of h~ */
        uint32_t m = 0;
        int32_t st, sv, lam_k, d, g, gc, gcn, epn, th_s, P_s, kn, kg = 0;
        int32_t il;
        int low;
        int tail = 1;       /* the forgetting scale and the block exponent still to do */
        int fixed_step = 0; /* the fixed-n step took c <- c / lambda_k */

        /* h~ = P~ phi, rounded and stored; m = OR of |h~_i| (one's complement) for the
         * normalisation below; s~ = phi' h~ (a) summed as h~ is stored */
        a = 0;
        if (!CANRLS_SMALL && (uint32_t)(h_os - 1) < 31u) {
            /* 1 <= h_os <= 31 (the common case): each sum rounded in two words (built for
             * size: store below, the same integers) */
#if CANRLS_FAST
            if (WIDE(S) & WIDE_H) {
                a = h_rows_full(P, phg, h, h_os, &c_h, &m);
            } else {
                a = h_rows_word(P, phg, h, h_os, h_lo, h_hi, &c_h, &m);
            }
#else
            /* h~ = P~ phi (+ the rounding half)   (symmetric: each P~_ij read once) */
            h_sums(P, phg, n, (int64_t)1 << (h_os - 1), acc);
            for (i = 0; i < n; i++) {
                const int32_t hi_ = h_word((uint64_t)acc[i], h_os, h_lo, h_hi, &c_h, 0);
                h[i] = hi_;
                m |= (uint32_t)(hi_ ^ (hi_ >> 31));
                /* s~ = phi' h~ (summed as h~ is stored) */
                a += (int64_t)phg[i] * hi_;
            }
#endif
        } else {
            /* h~ = P~ phi   (symmetric: each P~_ij of the upper triangle read once) */
            h_sums(P, phg, n, 0, acc);
            for (i = 0; i < n; i++) {
                const int32_t hi_ = store(acc[i], h_os, h_lo, h_hi, &c_h);
                h[i] = hi_;
                m |= (uint32_t)(hi_ ^ (hi_ >> 31));
                a += (int64_t)phg[i] * hi_;
            }
        }

        /* s~ = phi' h~ (a, summed above), brought from the scale of P (exponent e) to
         * that of lambda */
        st = store(!CANRLS_SMALL && (uint32_t)(e - 1) < 31u ? rsh_c(a, e, SHIFT_LOW)
                                                            : rsh_c(a, e, shift_class(e)),
                   p->s_os, p->den_lo, p->den_hi, &c_den);
        /* s = phi' P phi = c s~ */
        sv = store(mul_ww(st, c), p->sc_s, p->den_lo, p->den_hi, &c_den);

        /* windup <=> (tr P - g h'h)/lambda > trace_max
         *        <=> (tr P - lambda trace_max) (lambda + phi'P phi) > h'h */
        lam_k = p->lam_den;
        if (e >= S->wu_lo && e <= S->wu_hi) { /* trace_max_lam <= trace_max_lim >> e */
            /* tr P = c tr P~   (trw: the diagonal summed >> tr_ps, kept from the last row) */
            /* (lambda trace_max 2^e: within trace_max_lim for these e, so the shift is
             * the product) */
            int64_t T = rsh_w(mul_ww(trw, c), p->tc_s)
                        - (int64_t)((uint64_t)(int64_t)S->plan->trace_max_lam << e);
            if (T > 0 && windup_up(S, T, sv)) {
                lam_k = p->one_den;
                flag = CANRLS_FLAG_WINDUP;
            }
        }

        /* d = lambda_k + phi' P phi */
        d = add_sat(lam_k, sv, p->den_lo, p->den_hi, &c_den, 0);
        /* g = 1 / d     (the one division: acc-width dividend, word divisor, C truncation) */
        if (d <= 0) {
            g = p->g_hi;
            c_div += 1u;
        } else {
            /* DIVIDEND // d > g_hi  <=>  DIVIDEND >= (g_hi + 1) d : then the quotient
             * fits 32 bits, and a 64/32 division gives it */
            /* (g_hi + 1) d: 0 < g_hi + 1 <= 2^31 and 0 < d < 2^31, one 32 x 32 product */
            /* g normalised: g 2^kg = DIVIDEND 2^kg / d, kg = bit length of d - kg_bl within
             * [0, kg_max] and the room of the shifts below (kg = 0 for d < 2: the
             * steady state) */
            uint64_t dvd;
            kg = 32 - nlz((uint32_t)d) - p->kg_bl;
            if (UNLIKELY(kg > 0)) {
                /* kg <= min(kg_max, 62 - max(P_s, theta_s) - e) */
                const int32_t ps = p->P_s > p->theta_s ? p->P_s : p->theta_s;
                const int32_t lim = 62 - ps - e;
                kg = kg < p->kg_max ? kg : p->kg_max;
                kg = kg < lim ? kg : lim;
            } else {
                kg = 0;
            }
            dvd = (uint64_t)p->dividend << kg;
            if (dvd >= (uint64_t)((uint32_t)p->g_hi + 1u) * (uint32_t)d) {
                g = p->g_hi;
                c_div += 1u;
            } else {
                g = (int32_t)div_u64_u32(dvd, (uint32_t)d);
            }
        }
        /* gc = g c */
        gc = store(mul_ww(g, c), p->gc_s, p->g_lo, p->g_hi, &c_div);

        /* normalisation of the updates (once per step): h~ and eps shifted left (exactly)
         * to 31 bits, so that K is the high word of a 32 x 32 product and the theta and
         * P updates shift by 32 or more (docs/fixed_point.md) */
        {
            int32_t ke, lim;
            kn = norm_shift(m);
            lim = (62 - p->P_s - e - kg) >> 1;
            kn = kn < lim ? kn : lim;
            lim = 62 - p->theta_s - e - kg;
            kn = kn < lim ? kn : lim;
            ke = norm_shift((uint32_t)(eps ^ (eps >> 31)));
            lim = 62 - p->theta_s - e - kn - kg;
            ke = ke < lim ? ke : lim;
            epn = (int32_t)((uint32_t)eps << ke);
            gcn = (int32_t)((uint32_t)gc << p->g_up);
            th_s = p->theta_s + e + kn + ke + kg;
            /* K h~' has exponent 2e, P~ exponent e; K and h~ carry 2^kn each, g 2^kg */
            P_s = p->P_s + e + 2 * kn + kg;
        }
        il = (flag & CANRLS_FLAG_WINDUP) ? p->one_lam : p->inv_lam;
#if CANRLS_FAST
        if ((~WIDE(S) & (WIDE_THETA | WIDE_P)) == 0u && P_s >= 1) {
            /* 32-bit words at a fixed n: the step, the forgetting scale and the block
             * exponent in one pass over P (a c to fold is left to the code below) */
            if (P_s >= 33 && th_s >= 33) {
                low = KP_step_common(S, kn, gcn, epn, th_s, P_s, il, &e, &c, &trw, &c_th,
                                     &c_P);
            } else if (P_s >= 33) {
                low = KP_step_high(S, kn, gcn, epn, th_s, P_s, il, &e, &c, &trw, &c_th, &c_P);
            } else if (P_s == 32) {
                low = KP_step_32(S, kn, gcn, epn, th_s, P_s, il, &e, &c, &trw, &c_th, &c_P);
            } else {
                low = KP_step_low(S, kn, gcn, epn, th_s, P_s, il, &e, &c, &trw, &c_th, &c_P,
                                  m << kn);
            }
            tail = c > p->one_lam;
            fixed_step = 1;
        } else
#endif
        if (CANRLS_SMALL) {
            /* one instance of each (any shift: the same integers as the classes below) */
            K_step(S, kn, gcn, epn, th_s, &c_th, SHIFT_ANY, 0);
            low = P_step(S, P_s, &c_P, SHIFT_VAR, 0);
        } else {
        switch (shift_class(th_s)) {
        case SHIFT_HIGH:
            /* words of 32 bits: the overflow test is the clamp (th_s >= 34: the high word
             * of K eps times 2^(64 - th_s) is one SMULL) */
            if ((WIDE(S) & WIDE_THETA) && th_s >= 34) {
                K_step(S, kn, gcn, epn, th_s, &c_th, SHIFT_HIGH, 1);
            } else {
                K_step(S, kn, gcn, epn, th_s, &c_th, SHIFT_HIGH, 0);
            }
            break;
        case SHIFT_32:
            K_step(S, kn, gcn, epn, th_s, &c_th, SHIFT_32, 0);
            break;
        case SHIFT_LOW:
            K_step(S, kn, gcn, epn, th_s, &c_th, SHIFT_LOW, 0);
            break;
        default:
            K_step(S, kn, gcn, epn, th_s, &c_th, SHIFT_ANY, 0);
            break;
        }
        /* P <- (P - g (P phi)(P phi)') / lambda:  P~ <- P~ - K h~'   upper triangle
         * (in a loop made for the shift class of this step); low excitation: the
         * information K_i h~_i rounds to zero on the whole diagonal */
        switch (shift_class(P_s)) {
        case SHIFT_HIGH:
            /* words of 32 bits: the overflow test is the clamp (P_s >= 34: 2^(64 - P_s)
             * is a word, one SMULL) */
            if ((WIDE(S) & WIDE_P) && P_s >= 34) {
                low = P_step_high_full(S, P_s, &c_P);
            } else {
                low = P_step(S, P_s, &c_P, SHIFT_HIGH, 0);
            }
            break;
        case SHIFT_32:
            low = P_step(S, P_s, &c_P, SHIFT_32, 0);
            break;
        case SHIFT_LOW:
            low = P_step(S, P_s, &c_P, SHIFT_LOW, 0);
            break;
        default:
            low = P_step(S, P_s, &c_P, SHIFT_ANY, 0);
            break;
        }
        }
        if (low) {
            flag |= CANRLS_FLAG_LOW_EXCITATION;
        }

        /* c <- c / lambda_k (the fixed-n step: done) */
        if (tail && !fixed_step) {
            c = store(mul_ww(c, il), p->c_s, 0, p->lam_hi, &c_P);
        }
        if (tail && c > p->one_lam) {
            if (e > 0) {
                /* c/2 and 2^-e x 2: the words do not move */
                c = rsh32(c, 1);
                e -= 1;
            } else {
                /* fold c into P~: V <- rsh(V c, c_s) in 64 bits, c = 1 */
                for (i = 0; i < CANRLS_TRI(n); i++) {
                    P_fold(&P[i], c, p->c_s, p->P_lo, p->P_hi, &c_P);
                }
                c = p->one_lam;
            }
        }

        /* block exponent: tr P~ fell to tr_hi/2 or below -> shift left by sh, e += sh */
        if (tail) {
            int64_t tr = 0;
            uint32_t trw32 = 0; /* the sum modulo 2^32: trw is a word */
            const canrls_P64 *Pii = P;
            if (!CANRLS_SMALL && tr_ps > 0) {
                UNROLL
                for (i = 0; i < n; i++) {
                    const int32_t x = Pii->word;
                    tr += x;
                    trw32 += (uint32_t)(((x >> (tr_ps - 1)) + 1) >> 1);
                    Pii += n - i;
                }
            } else {
                for (i = 0; i < n; i++) {
                    tr += Pii->word;
                    trw32 += (uint32_t)rsh32(Pii->word, tr_ps); /* the word for tr_ps <= 0 */
                    Pii += n - i;
                }
            }
            trw = (int32_t)trw32;
            if (tr > 0 && tr <= (p->trace_hi >> 1) && e < p->e_max) {
                int32_t sh = 1;
                while ((tr << (sh + 1)) <= p->trace_hi && e + sh < p->e_max) {
                    sh += 1;
                }
                /* P~ <- P~ 2^sh: V <- V 2^sh exactly, the words and their fractions */
                for (i = 0; i < CANRLS_TRI(n); i++) {
                    P_shift(&P[i], sh, p->P_lo, p->P_hi, &c_P);
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
        const uint32_t nsat = c_phi + c_y + c_eps + c_h + c_den + c_div + c_th + c_P;
        if (nsat > 0u) {
            uint32_t *const cnt = S->counts;
            flag |= CANRLS_FLAG_SATURATION;
            cnt[CANRLS_S_PHI_IN] += c_phi;
            cnt[CANRLS_S_Y_IN] += c_y;
            cnt[CANRLS_S_EPS] += c_eps;
            cnt[CANRLS_S_H] += c_h;
            cnt[CANRLS_S_DEN] += c_den;
            cnt[CANRLS_S_DIV] += c_div;
            cnt[CANRLS_S_THETA] += c_th;
            cnt[CANRLS_S_P] += c_P;
        }
    }
    if (step != NULL) {
        /* tr P = c tr P~, recorded at the scale 2^-(f_P - tr_ps + e) */
        step->eps = eps;
        step->trace = (int32_t)mul_rsh(trw, c, p->tc_s, shift_class(p->tc_s));
        step->e = e;
        step->flags = flag;
    }
    return applied;
}
