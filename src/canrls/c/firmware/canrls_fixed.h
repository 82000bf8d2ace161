/*
 * canrls_fixed.h -- fixed-point recursive least squares, the embedded kernel.
 *
 * SPDX-License-Identifier: MIT
 *
 * A portable C99 transcription of the Python specification
 * (src/canrls/estimation/fixed/estimator.py, fixed_kernels.py: fixed_block, update="symmetric").
 * For the same plan, state and quantised inputs it produces the same integers, bit
 * for bit (tests/firmware/test_ckernel.py proves it on x86-64 and 32-bit ARM).
 *
 * Shape (CMSIS-DSP): the caller owns an instance struct (canrls_rls_q31), fills it
 * with canrls_init_q31() (or canrls_restore_q31() from a checkpoint) and calls
 * canrls_update_q31() once per sample. No malloc, no floating point, no libc beyond
 * <stdint.h>, <stddef.h> and memset (none built for size); the model size is bounded at
 * compile time by CANRLS_N_MAX (canrls_bounds.h).
 * Built with -DCANRLS_N=n (1 <= n <= CANRLS_N_MAX), the kernel is made for that one n:
 * its loops over n unrolled for the common case, the same integers, and
 * canrls_init_q31() accepting only n = CANRLS_N (docs/fixed_point.md, "A fixed n").
 * Built for size (CANRLS_SMALL: 1 by default under -Os, __OPTIMIZE_SIZE__; or
 * -DCANRLS_SMALL=1), it keeps its loops and one general instance of each step, the
 * same integers again: -O2 for speed, -Os for size.
 *
 * Numbers
 * -------
 * Every quantity is a signed two's-complement word of at most 32 bits held in an
 * int32_t ("q31" here means "a word of <= 32 bits in an int32_t"; its Q format,
 * Qm.f with f fraction bits, is the one the Python FixedConfig chose and is stated
 * below per quantity). Products of two words are exact (int64_t). A value is brought
 * to a coarser scale by a rounding right shift, round half up:
 *     rsh(x, s) = (x + 2^(s-1)) >> s          (arithmetic shift)
 * then clamped to its word [lo, hi]; every clamp increments the counter of its site
 * (canrls_site). Nothing wraps. Multiply-accumulates sum at most n products in an
 * int64_t accumulator that cannot overflow: the plan's guard shift phi_ps makes it
 * so for every input.
 *
 * The covariance is held scaled:  P = c * P~ * 2^-(f_P + e)
 *   P~  in 64 bits (upper triangle only, packed by rows: canrls_P64), the word Pw in the
 *       P format (P~ rounded half up: what h, the trace and the block exponent read)
 *       and a fraction below it,
 *   e   block exponent, 0 <= e <= e_max,
 *   c   forgetting scale in the lam format, 1/2 < c <= 1 (one_lam = 1.0).
 *
 * Per sample (the equation of each line is beside it in canrls_fixed.c):
 *   eps   = y - phi' theta
 *   h     = Pw phi,  d = lambda_k + c phi' h,  g = 1/d   (one division, g normalised by
 *           2^kg when d is large)
 *   K     = (g c) h     (the high word of (h 2^kn)(g c 2^g_up), kn normalising h)
 *   theta = theta + K eps   (in 64 bits, theta_q: the word theta and its fraction)
 *   P~    = P~ - K h'   (upper triangle, in 64 bits),  c = c / lambda_k
 * with lambda_k = 1 (flag WINDUP) when the step would take tr P above trace_max.
 *
 * Constants
 * ---------
 * The kernel never derives a constant: every shift, range and Q constant of
 * lambda is in canrls_plan_q31, with the names of the Python FixedRLS.constants.
 * canrls_init_q31() only evaluates, once, two tests of the plan the update would
 * otherwise repeat (which words are the whole int32_t; for which block exponents the
 * windup test runs) and keeps the answers in the instance.
 * canrls.firmware.kernel_export.plan_c (and `canrls export-c`) writes it as a C initialiser from a
 * Python FixedRLS.
 */
#ifndef CANRLS_FIXED_H
#define CANRLS_FIXED_H

#include <stddef.h>
#include <stdint.h>
#include <string.h>

#ifdef __cplusplus
extern "C" {
#endif

/* CANRLS_N_MAX, the largest number of parameters (compile-time bound of the instance
 * arrays): the build's bounds, canrls_bounds.h */
#include "canrls_bounds.h"

/** Built for size: 1 by default where the compiler optimises for size (GCC's and Clang's
 * __OPTIMIZE_SIZE__ at -Os), or -DCANRLS_SMALL=1 / =0: loops and one instance of each step
 * in the kernel, the rare steps of canrls_target.c out of line (the same integers). */
#ifndef CANRLS_SMALL
#if defined(__OPTIMIZE_SIZE__)
#define CANRLS_SMALL 1
#else
#define CANRLS_SMALL 0
#endif
#endif

/** Packed upper triangle of an n x n matrix: n (n + 1) / 2 words. */
#define CANRLS_TRI(n) ((n) * ((n) + 1) / 2)

/** Saturation sites, in the order of canrls_rls_q31.counts (Python SITES). */
enum canrls_site {
    CANRLS_S_PHI_IN = 0, /**< an input phi_j outside its word */
    CANRLS_S_Y_IN,       /**< the output y outside its word */
    CANRLS_S_EPS,        /**< a-priori error */
    CANRLS_S_H,          /**< h = Pw phi */
    CANRLS_S_DEN,        /**< phi' h and d = lambda_k + phi' P phi */
    CANRLS_S_DIV,        /**< the quotient g = 1/d and g c */
    CANRLS_S_K,          /**< the gain K */
    CANRLS_S_THETA,      /**< theta + K eps */
    CANRLS_S_P,          /**< Pw - K h', c, the fold of c and the block-exponent shift */
    CANRLS_S_ACC,        /**< accumulators: 0 by construction (kept so every site is listed) */
    CANRLS_NSITES
};

/** Flag bits of a step (the values of Python FixedFlag / RLSFlag). */
#define CANRLS_FLAG_WINDUP         1u /**< trace bound held: step taken with lambda = 1 */
#define CANRLS_FLAG_LOW_EXCITATION 2u /**< K_i h_i rounded to 0 on the whole diagonal */
#define CANRLS_FLAG_SATURATION     4u /**< a counter moved during this step */
#define CANRLS_FLAG_FROZEN         8u /**< frozen: eps computed, state untouched */

/** Return codes of canrls_init_q31() and canrls_restore_q31(). */
#define CANRLS_OK        0
#define CANRLS_EINVAL  (-1)

/**
 * The kernel's integer constants: Python FixedRLS.constants, same names.
 *
 * `*_lo`, `*_hi`: the range of each word, -2^(bits-1) and 2^(bits-1) - 1.
 * `*_s`, `*_os`, `*_ps`: shifts (>= 0 unless stated), `*_ts`: alignment (> 0: left).
 * Built from the FixedConfig, n, the rational value of lambda and trace_max; a
 * change of lambda is a new plan.
 */
typedef struct {
    int32_t phi_lo, phi_hi;     /**< regressor word */
    int32_t y_lo, y_hi;         /**< output word */
    int32_t eps_lo, eps_hi;     /**< a-priori error word */
    int32_t h_lo, h_hi;         /**< h = Pw phi word */
    int32_t den_lo, den_hi;     /**< phi' P phi and d word */
    int32_t g_lo, g_hi;         /**< g = 1/d word (Q1) */
    int32_t K_lo, K_hi;         /**< gain word */
    int32_t theta_lo, theta_hi; /**< estimate word */
    int32_t P_lo, P_hi;         /**< covariance word */
    int32_t lam_lo, lam_hi;     /**< lambda, 1/lambda and c word (Q1) */
    int32_t phi_ps;         /**< guard shift of phi in the three multiply-accumulates */
    int32_t eps_ts;         /**< alignment of y to the phi' theta accumulator (may be < 0) */
    int32_t eps_os;         /**< output shift of eps (may be < 0) */
    int32_t h_os;           /**< output shift of h (may be < 0) */
    int32_t s_os;           /**< output shift of phi' h after >> e (may be < 0) */
    int32_t sc_s;           /**< shift of c s~ */
    int32_t lam_den;        /**< lambda in the den format */
    int32_t one_den;        /**< 1 in the den format */
    int64_t dividend;       /**< 1 << (frac_g + frac_den) */
    int32_t gc_s;           /**< shift of g c */
    int32_t g_up;           /**< left shift of g c to 32 bits (K: the high word) */
    int32_t kg_bl;          /**< g is normalised by 2^kg, kg = bit length of d - kg_bl (>= 0) */
    int32_t kg_max;         /**< largest kg (the dividend 2^kg in the accumulator) */
    int32_t theta_s;        /**< shift of K eps at e = kn = ke = kg = 0 (+ e + kn + ke + kg) */
    int32_t P_s;            /**< shift of K h at e = kn = kg = 0 (+ e + 2 kn + kg) */
    int32_t inv_lam;        /**< 1/lambda in the lam format */
    int32_t one_lam;        /**< 1 in the lam format */
    int32_t c_s;            /**< shift of c (1/lambda_k) and of the fold c Pw */
    int32_t trace_ps;       /**< guard shift of each diagonal word in the trace */
    int32_t tc_s;           /**< shift of c tr Pw */
    int32_t trace_max_lam;  /**< lambda trace_max at the trace's scale (e = 0) */
    int64_t trace_max_lim;  /**< the windup test runs while trace_max_lam << e <= this */
    int32_t hc_s;           /**< shift of c h (windup test) */
    int32_t vw_ps;          /**< pre-shift of h_i h_i (windup test) */
    int32_t lhs_ps;         /**< pre-shift of (tr P - lambda trace_max) d (windup test) */
    int32_t cmp_scale_diff; /**< scale difference of the two sides at e = 0 (may be < 0) */
    int32_t trace_hi;       /**< tr Pw is kept in (trace_hi/2, trace_hi] once e > 0 */
    int32_t e_max;          /**< largest block exponent */
} canrls_plan_q31;

/** The fields of canrls_plan_q31 in declaration order, as an X-macro: the order in which
 * the extensions canrls._fixed and canrls._target read a plan vector (exported to Python
 * as PLAN_FIELDS), and the fields the kernel compares with its constant plan. */
#define CANRLS_PLAN_FIELDS(X)                                                           \
    X(phi_lo) X(phi_hi) X(y_lo) X(y_hi) X(eps_lo) X(eps_hi) X(h_lo) X(h_hi) X(den_lo)    \
    X(den_hi) X(g_lo) X(g_hi) X(K_lo) X(K_hi) X(theta_lo) X(theta_hi) X(P_lo) X(P_hi)    \
    X(lam_lo) X(lam_hi) X(phi_ps) X(eps_ts) X(eps_os) X(h_os) X(s_os) X(sc_s) X(lam_den) \
    X(one_den) X(dividend) X(gc_s) X(g_up) X(kg_bl) X(kg_max) X(theta_s) X(P_s)          \
    X(inv_lam) X(one_lam) X(c_s) X(trace_ps) X(tc_s) X(trace_max_lam) X(trace_max_lim)    \
    X(hc_s) X(vw_ps) X(lhs_ps) X(cmp_scale_diff) X(trace_hi) X(e_max)

/** 8-byte alignment where the compiler has a way to say it (GCC, Clang): one LDRD/STRD
 * per canrls_theta64 on Cortex-M. Without it the layout and the integers are the same. */
#if defined(__GNUC__)
#define CANRLS_ALIGN8 __attribute__((aligned(8)))
#else
#define CANRLS_ALIGN8
#endif

/**
 * One parameter of the estimate in 64 bits: the value word 2^32 + frac, in units of
 * 2^-32 of theta's LSB. `word` is theta_j in the theta format (the word published and
 * used in eps = y - phi' theta: canrls_theta_q31()); `frac` is the estimate below its
 * LSB (canrls_theta_frac_q31()), so that updates smaller than the LSB accumulate. The
 * two words of a parameter are adjacent and 8-byte aligned: the update loads and stores
 * them together (LDRD/STRD on Cortex-M4).
 */
typedef struct {
    uint32_t frac; /**< the fraction below word's LSB, units of 2^-32 LSB */
    int32_t word;  /**< theta_j, theta format */
} CANRLS_ALIGN8 canrls_theta64;

/**
 * One element of P~ in 64 bits: the value V = P~_ij 2^32, in units of 2^-32 of the P
 * format's LSB. `word` is P~_ij rounded half up, rsh(V, 32), in the P format (the word
 * h = Pw phi, the trace and the block exponent read: canrls_P_q31()); below it the
 * fraction V - word 2^32, in [-2^31, 2^31), held in `lo` with 2^31 added
 * (canrls_P_frac_q31() gives the fraction): the pair word 2^32 + lo is then the 64-bit
 * two's-complement V + 2^31, and the update V - K_i h_j is one 64-bit subtraction
 * (SUBS/SBCS on the Cortex-M4, one LDRD and one STRD).
 */
typedef struct {
    uint32_t lo;  /**< the fraction below word, plus 2^31 (units of 2^-32 LSB) */
    int32_t word; /**< Pw_ij, P format: P~_ij rounded */
} CANRLS_ALIGN8 canrls_P64;

/**
 * Instance of the fixed-point RLS: owned by the caller, filled by canrls_init_q31().
 *
 * The state fields may be read at any time (theta_q through canrls_theta_q31() and
 * canrls_theta_frac_q31(), P through canrls_P_q31() and canrls_P_frac_q31(), e, c,
 * counts, K); write them only through canrls_restore_q31(), except `frozen` and
 * `counts` (plain fields).
 */
typedef struct {
    const canrls_plan_q31 *plan; /**< constants (not copied: keep it alive) */
    uint32_t n;                  /**< number of parameters, 1..CANRLS_N_MAX */
    uint32_t frozen;             /**< nonzero: updates compute eps only (flag FROZEN) */
    int32_t e;                   /**< block exponent of P */
    int32_t c;                   /**< forgetting scale of P (lam format) */
    int32_t trw;                 /**< sum of rsh(Pw_ii, trace_ps) (kept from step to step) */
    int32_t wu_lo, wu_hi;        /**< the windup test runs for wu_lo <= e <= wu_hi: the e with
                                      trace_max_lam <= trace_max_lim >> e (an interval, set
                                      by canrls_init_q31 from the plan) */
    uint32_t wide;               /**< bits 0..3: the phi, h, theta, P words are the whole
                                      int32_t (set by canrls_init_q31 from the plan) */
    canrls_theta64 theta_q[CANRLS_N_MAX]; /**< the estimate in 64 bits (see canrls_theta64):
                                               read it with canrls_theta_q31() and
                                               canrls_theta_frac_q31() */
    canrls_P64 P[CANRLS_TRI(CANRLS_N_MAX)]; /**< P~ in 64 bits (see canrls_P64), upper
                                                 triangle packed by rows: read it with
                                                 canrls_P_q31() and canrls_P_frac_q31() */
    int32_t K[CANRLS_N_MAX];     /**< gain of the last step (K 2^(f_K + e + kn + kg)), 0 when
                                      frozen */
    int32_t h[CANRLS_N_MAX];     /**< scratch: h = Pw phi (h format, normalised or not) */
    int32_t phg[CANRLS_N_MAX];   /**< scratch: phi >> phi_ps */
    uint32_t counts[CANRLS_NSITES]; /**< saturations per site (canrls_site), wrap at 2^32 */
} canrls_rls_q31;

/** What one update returns (Python FixedStep without K and theta, which stay in the instance:
 * S->K, canrls_theta_q31()). */
typedef struct {
    int32_t eps;    /**< a-priori error, eps format (saturated, counted) */
    int32_t trace;  /**< tr P after the step, 2^-(f_P - trace_ps + e) scale */
    int32_t e;      /**< block exponent after the step */
    uint32_t flags; /**< CANRLS_FLAG_* bits */
} canrls_step_q31;

/**
 * Initialise: theta = 0, P~ = diag(p0[0..n-1]) (fractions 0), block exponent e0, c = 1
 * (plan->one_lam), counters 0, not frozen.
 *
 * @param S     instance to fill
 * @param plan  constants (kept by pointer)
 * @param n     number of parameters, 1..CANRLS_N_MAX
 * @param p0    n diagonal words of the initial covariance, P format, in [P_lo, P_hi]
 *              (P0_jj = p0[j] 2^-(f_P + e0)); the off-diagonal words are 0
 * @param e0    initial block exponent, 0..plan->e_max
 * @return CANRLS_OK, or CANRLS_EINVAL for an n, p0 or e0 out of range, or an n other
 *         than CANRLS_N where the build fixes it (S untouched)
 */
int canrls_init_q31(canrls_rls_q31 *S, const canrls_plan_q31 *plan, uint32_t n,
                    const int32_t *p0, int32_t e0);

/**
 * Restore a checkpoint (Python FixedRLS.state()): theta, theta_frac, the upper triangle
 * of P~ (its words and their fractions), e and c (theta_q[j]: word theta[j], frac
 * theta_frac[j]). Counters and `frozen` are left as they are (plain fields).
 *
 * @param theta  n words, theta format
 * @param theta_frac  n fractions (state "theta_frac"), or NULL for zeros (a checkpoint
 *               of format canrls.fixed/1, written before the 64-bit estimate)
 * @param P_up   n (n + 1) / 2 words of P~'s upper triangle packed by rows, P format
 * @param P_frac_up  their n (n + 1) / 2 fractions in 2^-32 LSB, -2^31..2^31-1 (state
 *               "P_frac", the upper triangle packed by rows), or NULL for zeros (a
 *               checkpoint of format canrls.fixed/2 or /1, written before the 64-bit P)
 * @param e      block exponent, 0..plan->e_max
 * @param c      forgetting scale, lam format, 1..plan->one_lam
 * @return CANRLS_OK or CANRLS_EINVAL (a value outside its word; S untouched)
 */
int canrls_restore_q31(canrls_rls_q31 *S, const int32_t *theta, const uint32_t *theta_frac,
                       const int32_t *P_up, const int32_t *P_frac_up, int32_t e, int32_t c);

/**
 * One sample: the recursion of the module comment, in place.
 *
 * @param S     instance (state updated unless S->frozen)
 * @param phi   n regressor words, phi format (clamped to [phi_lo, phi_hi], counted phi_in)
 * @param y     output word, y format (clamped to [y_lo, y_hi], counted y_in)
 * @param step  optional result (eps, trace, e, flags); NULL to skip
 * @return 1 if the state was updated, 0 if frozen
 *
 * Saturates (each counted at its site): eps, h, phi' h and d (den), g and g c (div),
 * theta, P~ and c (P); K cannot (the high word of two normalised 31-bit words). S->K
 * holds the gain of this step.
 */
int canrls_update_q31(canrls_rls_q31 *S, const int32_t *phi, int32_t y,
                      canrls_step_q31 *step);

/**
 * The published estimate: the word theta_j (theta format) of parameter j
 * (S->theta_q[j].word). The value to use, log or send (the physical value is theta_j
 * 2^-f_theta, see the generated header of `canrls export-c`).
 */
static inline int32_t canrls_theta_q31(const canrls_rls_q31 *S, uint32_t j)
{
    return S->theta_q[j].word;
}

/**
 * The fraction of parameter j below theta_j's LSB, in units of 2^-32 LSB
 * (S->theta_q[j].frac; state "theta_frac" of a checkpoint, with canrls_theta_q31() its
 * "theta": what canrls_restore_q31() takes back).
 */
static inline uint32_t canrls_theta_frac_q31(const canrls_rls_q31 *S, uint32_t j)
{
    return S->theta_q[j].frac;
}

/**
 * The word of element k of P~'s packed upper triangle (P format: P~ rounded half up;
 * S->P[k].word; the checkpoint's "P", the triangle packed by rows).
 */
static inline int32_t canrls_P_q31(const canrls_rls_q31 *S, size_t k)
{
    return S->P[k].word;
}

/**
 * The fraction of element k of P~'s packed upper triangle below its word, in units of
 * 2^-32 LSB, -2^31..2^31-1 (S->P[k].lo - 2^31; the checkpoint's "P_frac": what
 * canrls_restore_q31() takes back).
 */
static inline int32_t canrls_P_frac_q31(const canrls_rls_q31 *S, size_t k)
{
    return (int32_t)(S->P[k].lo ^ 0x80000000u);
}

/** Set `size` bytes at p to the byte c (a state, a scratch array): libc's memset, or a
 * loop of byte stores (a char may alias any object) when built for size, so that the
 * estimator links no memset (164 B at -Os in newlib-nano). */
static inline void canrls_fill(void *p, unsigned char c, size_t size)
{
#if CANRLS_SMALL
    unsigned char *b = (unsigned char *)p;
    while (size-- != 0u) {
#if defined(__GNUC__)
        __asm__("" : "+r"(b)); /* keeps GCC from turning the loop back into memset */
#endif
        *b++ = c;
    }
#else
    memset(p, c, size);
#endif
}

/** Index of Pw_ij (i <= j) in the packed upper triangle of an n x n matrix. */
static inline size_t canrls_tri_index(uint32_t n, uint32_t i, uint32_t j)
{
    return (size_t)i * n - (size_t)i * (i - 1u) / 2u + (j - i);
}

#ifdef __cplusplus
}
#endif

#endif /* CANRLS_FIXED_H */
