/*
 * kernels.c -- canrls._kernels: the per-sample float kernels of the estimation.
 *
 * SPDX-License-Identifier: MIT
 *
 * One implementation for the live daemon and the offline replay: the float RLS
 * (symmetric and literal, float64 and float32), the state-variable filter, the sample
 * selection, the position unwrapping and the pipeline's bookkeeping sums (and the
 * harmonic columns of the diagnosis's order spectrum). Each kernel
 * is the loop the Python module describes, with the same operations in the same order
 * (the equation beside each line), so a recording gives the same bits wherever it is
 * processed. Built with -ffp-contract=off and without -ffast-math: no fused
 * multiply-add, no reassociation.
 *
 * Arrays come in through the buffer protocol (any C-contiguous buffer of the right
 * item type: numpy arrays in practice), so building needs only the Python headers,
 * not numpy's. Each wrapper checks the item type, the number of dimensions and the
 * sizes it indexes (a wrong call raises TypeError or ValueError, it never reads out
 * of bounds); the semantic checks stay in the Python classes. The loops run without
 * the GIL.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <float.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

#include "pyargs.h"

#if !defined(FLT_EVAL_METHOD) || FLT_EVAL_METHOD != 0
#error "the float32 kernels need FLT_EVAL_METHOD == 0 (float arithmetic in float)"
#endif

/* Flag bits; the same values as canrls.estimation.rls.RLSFlag (checked by a test). */
#define FLAG_WINDUP 1
#define FLAG_FROZEN 8
#define FLAG_NONFINITE 16

/* ------------------------------------------------------------------ float RLS */
#define REAL double
#define RLS(name) name##_f64
#include "kernels_rls.h"
#undef REAL
#undef RLS

#define REAL float
#define RLS(name) name##_f32
#include "kernels_rls.h"
#undef REAL
#undef RLS

/* ------------------------------------------------------- state-variable filter */
/* Advance every column's state (x1, x2) and previous input up to row u (m values);
 * the first sample ever (*primed == 0) starts at rest. G0, G1 are (m, 2): the input
 * coefficients of each column's hold, Ad is (2, 2). */
static void svf_step(Py_ssize_t m, const double *u, const double *Ad, const double *G0,
                     const double *G1, double *x1, double *x2, double *up, int64_t *primed)
{
    if (*primed == 0) {
        /* start at rest on the first sample: x = [u0, 0] */
        for (Py_ssize_t j = 0; j < m; j++) {
            x1[j] = u[j];
            x2[j] = 0.0;
            up[j] = u[j];
        }
        *primed = 1;
        return;
    }
    for (Py_ssize_t j = 0; j < m; j++) {
        const double uk = u[j];
        /* x[k] = Ad x[k-1] + G0 u[k-1] + G1 u[k] */
        const double n1 = Ad[0] * x1[j] + Ad[1] * x2[j] + G0[2 * j] * up[j] + G1[2 * j] * uk;
        const double n2 = Ad[2] * x1[j] + Ad[3] * x2[j] + G0[2 * j + 1] * up[j]
                          + G1[2 * j + 1] * uk;
        x1[j] = n1;
        x2[j] = n2;
        up[j] = uk;
    }
}

/* Filter every column of u (N, m) row by row; f gets x1 and sf x2 of every row. */
static void svf(Py_ssize_t N, Py_ssize_t m, const double *u, const double *Ad,
                const double *G0, const double *G1, double *x1, double *x2, double *up,
                int64_t *primed, double *f, double *sf)
{
    for (Py_ssize_t k = 0; k < N; k++) {
        svf_step(m, u + k * m, Ad, G0, G1, x1, x2, up, primed);
        for (Py_ssize_t j = 0; j < m; j++) {
            f[k * m + j] = x1[j];
            sf[k * m + j] = x2[j];
        }
    }
}

/* svf() writing one output per column: x2 where deriv else x1, times scale (exact
 * powers of two); column 0 into y (N), the others into phi (N, m-1). */
static void svf_scaled(Py_ssize_t N, Py_ssize_t m, const double *u, const double *Ad,
                       const double *G0, const double *G1, double *x1, double *x2,
                       double *up, int64_t *primed, const uint8_t *deriv,
                       const double *scale, double *y, double *phi)
{
    for (Py_ssize_t k = 0; k < N; k++) {
        svf_step(m, u + k * m, Ad, G0, G1, x1, x2, up, primed);
        y[k] = (deriv[0] ? x2[0] : x1[0]) * scale[0];
        for (Py_ssize_t j = 1; j < m; j++)
            phi[k * (m - 1) + j - 1] = (deriv[j] ? x2[j] : x1[j]) * scale[j];
    }
}

/* ------------------------------------------------------------ sample selection */
/* Mark gaps (restart the filter there) and the rows not to use; count both.
 * A row is not used in the warm-up after a restart, nor while |omega| > max_speed or
 * |omega| < min_speed, nor in the warm-up after those. With min_speed > 0 a sign
 * change of omega since the last sample counts as a speed below min_speed: the drive
 * passed through zero between the two samples, however fast it reversed.
 * state = [last t (nan: none yet), samples left in the warm-up, last omega] */
static void select_rows(Py_ssize_t N, const double *t, const double *omega, double gap,
                        int64_t warm, double min_speed, double max_speed, double *state,
                        uint8_t *restart, uint8_t *use, Py_ssize_t *restarts,
                        Py_ssize_t *used)
{
    double last = state[0];
    double left = state[1];
    double w_last = state[2];
    Py_ssize_t r = 0, u = 0;
    for (Py_ssize_t k = 0; k < N; k++) {
        if (last != last || t[k] - last > gap || t[k] < last) {
            restart[k] = 1;
            r++;
            left = (double)warm;
            w_last = 0.0;  /* no crossing across a restart */
        }
        last = t[k];
        const double w = fabs(omega[k]);
        /* omega_{k-1} omega_k < 0: a zero crossing between the samples */
        const int crossed = min_speed > 0 && w_last * omega[k] < 0;
        if (w > max_speed || w < min_speed || crossed)
            left = (double)(warm + 1);
        if (omega[k] == omega[k])
            w_last = omega[k];
        if (left > 0) {
            use[k] = 0;
            left -= 1;
        } else {
            use[k] = 1;
            u++;
        }
    }
    state[0] = last;
    state[1] = left;
    state[2] = w_last;
    *restarts = r;
    *used = u;
}

/* True when no step between samples (from last_t if has_last) misses a period: each
 * rounds to at most one period, is longer than max_gap or is not forward (a nan step
 * is left to GapFiller.fill). */
static int nothing_to_fill(Py_ssize_t N, const double *t, int has_last, double last_t,
                           double dt, double max_gap)
{
    double prev = has_last ? last_t : t[0];
    for (Py_ssize_t k = 0; k < N; k++) {
        const double gap = t[k] - prev;
        prev = t[k];
        if (!(gap > max_gap || gap <= 0.0 || rint(gap / dt) <= 1.0))
            return 0;
    }
    return 1;
}

/* -------------------------------------------------------------- unwrapping */
/* Unwrapped p into out, from the turn count turns and the previous sample last (nan:
 * none, no jump before the first sample); returns the turn count at the end. */
static int64_t unwrap(Py_ssize_t N, const double *p, double period, int64_t turns,
                      double last, double *out)
{
    double prev = last != last ? p[0] : last;
    for (Py_ssize_t k = 0; k < N; k++) {
        const double d = p[k] - prev;
        if (isfinite(d))
            /* one wrap per half-period jump, opposite to the jump */
            turns -= (int64_t)rint(d / period);
        /* theta = p + turns * period (turns exact integers: the same whatever the blocks) */
        out[k] = p[k] + (double)turns * period;
        prev = p[k];
    }
    return turns;
}

/* ------------------------------------------------------------ pipeline sums */
/* Sequential sums over used rows: M += phi phi' (upper triangle), v += phi y,
 * s = [N, sum y, sum y^2]. */
static void accumulate(Py_ssize_t N, Py_ssize_t n, const double *phi, const double *y,
                       const uint8_t *use, double *M, double *v, double *s)
{
    for (Py_ssize_t k = 0; k < N; k++) {
        if (!use[k])
            continue;
        const double yk = y[k];
        const double *row = phi + k * n;
        for (Py_ssize_t i = 0; i < n; i++) {
            const double pi = row[i];
            /* v += phi y */
            v[i] += pi * yk;
            for (Py_ssize_t j = i; j < n; j++)
                /* M += phi phi' */
                M[i * n + j] += pi * row[j];
        }
        s[0] += 1.0;
        s[1] += yk;
        s[2] += yk * yk;
    }
}

/* After the estimators, row by row: spread the used rows' errors and flags over the
 * block (0 elsewhere), run the residual RMS, write y, the errors and the RMS in the
 * output unit (x 2**s_y); accumulate the sums. Returns the float WINDUP count.
 * eps_u, flags_u (float) and epsq_u, flagsq_u (fixed point) hold the used rows only;
 * the fixed-point error is epsq * lsb with lsb = 2**-frac, exact. */
static Py_ssize_t bookkeeping(Py_ssize_t N, Py_ssize_t n, const double *phi,
                              const double *y, const uint8_t *use, const double *eps_u,
                              const int64_t *epsq_u, double lsb, const uint8_t *flags_u,
                              const uint8_t *flagsq_u, double *M, double *v, double *s,
                              double beta, double *rms_state, int64_t s_y, double *y_out,
                              double *eps, double *eps_fixed, uint8_t *flags, double *rms)
{
    /* x 2**s_y: the product with the exact power of two rounds once, as ldexp does */
    const int exact = -1074 <= s_y && s_y <= 1023;
    const double unit = exact ? ldexp(1.0, (int)s_y) : 0.0;
    /* ldexp's exponent as an int (an exponent beyond these gives 0 or inf all the same) */
    const int sy = s_y < -4000 ? -4000 : s_y > 4000 ? 4000 : (int)s_y;
    double r = rms_state[0];
    Py_ssize_t windup = 0;
    Py_ssize_t i = 0;
    for (Py_ssize_t k = 0; k < N; k++) {
        double e = 0.0;
        double ef = 0.0;
        uint8_t f = 0;
        if (use[k]) {
            e = eps_u[i];
            /* eps_fixed = epsq 2**-frac */
            ef = (double)epsq_u[i] * lsb;
            f = flags_u[i] | flagsq_u[i];
            if (flags_u[i] & FLAG_WINDUP)
                windup++;
            /* exponentially weighted mean square: r <- r + beta (eps^2 - r) on used rows */
            r += beta * (e * e - r);
            i++;
        }
        flags[k] = f;
        if (exact) {
            y_out[k] = y[k] * unit;
            eps[k] = e * unit;
            eps_fixed[k] = ef * unit;
            rms[k] = sqrt(r) * unit;
        } else {
            y_out[k] = ldexp(y[k], sy);
            eps[k] = ldexp(e, sy);
            eps_fixed[k] = ldexp(ef, sy);
            rms[k] = ldexp(sqrt(r), sy);
        }
    }
    rms_state[0] = r;
    accumulate(N, n, phi, y, use, M, v, s);
    return windup;
}

/* ---------------------------------------------- harmonic columns (diagnosis) */
/* The unfiltered columns of the residual's order spectrum
 * (canrls.diagnosis.residual.harmonic_fit), for angles a (N) and orders q (m), into out
 * (N, 2m): out[i, 2j] = sin(q_j a_i), out[i, 2j + 1] = cos(q_j a_i). */
static void sincos_columns(Py_ssize_t N, Py_ssize_t m, const double *a, const double *q,
                           double *out)
{
    for (Py_ssize_t i = 0; i < N; i++)
        for (Py_ssize_t j = 0; j < m; j++) {
            /* x = q_j a_i */
            const double x = q[j] * a[i];
            out[i * 2 * m + 2 * j] = sin(x);
            out[i * 2 * m + 2 * j + 1] = cos(x);
        }
}

/* ================================================================= Python glue */
/* The argument helpers (item types, shapes, numbers) are in pyargs.h. */

/* Whether o is a float32 buffer (the precision of an RLS state; anything else is
 * taken as float64, and take() says what is wrong with it). */
static int is_single(PyObject *o)
{
    Py_buffer b;
    if (PyObject_GetBuffer(o, &b, PyBUF_FORMAT | PyBUF_ND) < 0) {
        PyErr_Clear();
        return 0;
    }
    const int single = is_kind(&b, F32);
    PyBuffer_Release(&b);
    return single;
}

/* ------------------------------------------------------------------ RLS glue */
typedef Py_ssize_t (*rls64_fn)(Py_ssize_t, Py_ssize_t, const double *, const double *,
                               double *, double *, double *, double *, double, double, int,
                               int, double *, double *, double *, uint8_t *);
typedef Py_ssize_t (*rls32_fn)(Py_ssize_t, Py_ssize_t, const float *, const float *,
                               float *, float *, float *, float *, float, float, int, int,
                               float *, float *, float *, uint8_t *);

static PyObject *rls_call(const char *fn, rls64_fn k64, rls32_fn k32, PyObject *const *args,
                          Py_ssize_t nargs)
{
    static const Spec spec[] = {
        {0, "Phi", REAL_, 2, RO}, {1, "Y", REAL_, 1, RO}, {2, "theta", REAL_, 1, RW},
        {3, "P", REAL_, 2, RW}, {4, "work", REAL_, 2, RW}, {5, "acc", REAL_, 1, RW},
        {10, "eps_out", REAL_, 1, RW}, {11, "theta_out", REAL_, 2, RW},
        {12, "trace_out", REAL_, 1, RW}, {13, "flags_out", U8, 1, RW},
    };
    Args a = {.fn = fn, .count = 0};
    Py_buffer *b[COUNT(spec)];
    double lam, trace_max;
    int frozen, record;
    PyObject *res = NULL;
    if (!start(&a, nargs, 14) || !as_double(args[6], &lam) || !as_double(args[7], &trace_max)
        || !as_bool(args[8], &frozen) || !as_bool(args[9], &record))
        return NULL;
    /* the dtype of the state decides the precision: theta's */
    const int single = is_single(args[2]);
    if (take(&a, args, spec, COUNT(spec), b, single ? F32 : F64)) {
        Py_buffer *Phi = b[0], *Y = b[1], *theta = b[2], *P = b[3], *work = b[4], *acc = b[5],
                  *eps = b[6], *th = b[7], *tr = b[8], *fl = b[9];
        const Py_ssize_t n = dim(theta, 0), N = dim(Phi, 0);
        if (need(&a, Phi, "Phi", N, n) && need(&a, Y, "Y", N, -1) && need(&a, P, "P", n, n)
            && need(&a, work, "work", 3, n) && need(&a, acc, "acc", 2, -1)
            && need(&a, eps, "eps_out", N, -1) && need(&a, tr, "trace_out", N, -1)
            && need(&a, fl, "flags_out", N, -1)
            && need(&a, th, "theta_out", record ? N : dim(th, 0), n)) {
            Py_ssize_t applied;
            Py_BEGIN_ALLOW_THREADS
            if (single)
                applied = k32(N, n, F(Phi), F(Y), F(theta), F(P), F(work), F(acc), (float)lam,
                              (float)trace_max, frozen, record, F(eps), F(th), F(tr), U(fl));
            else
                applied = k64(N, n, D(Phi), D(Y), D(theta), D(P), D(work), D(acc), lam,
                              trace_max, frozen, record, D(eps), D(th), D(tr), U(fl));
            Py_END_ALLOW_THREADS
            res = PyLong_FromSsize_t(applied);
        }
    }
    release(&a);
    return res;
}

PyDoc_STRVAR(rls_block_symmetric_doc,
"rls_block_symmetric(Phi, Y, theta, P, work, acc, lam, trace_max, frozen, record,\n"
"                    eps_out, theta_out, trace_out, flags_out) -> int\n\n"
"The symmetric RLS update over the rows of Phi, in place; the number of rows applied.\n"
"float64 or float32 (theta's dtype; every array the same). See\n"
"canrls.estimation.rls.KERNELS for the arguments.");

static PyObject *py_rls_block_symmetric(PyObject *self, PyObject *const *args,
                                        Py_ssize_t nargs)
{
    (void)self;
    return rls_call("rls_block_symmetric", rls_block_symmetric_f64, rls_block_symmetric_f32,
                    args, nargs);
}

PyDoc_STRVAR(rls_block_literal_doc,
"rls_block_literal(...) -> int\n\n"
"The textbook RLS update; the arguments of rls_block_symmetric.");

static PyObject *py_rls_block_literal(PyObject *self, PyObject *const *args,
                                      Py_ssize_t nargs)
{
    (void)self;
    return rls_call("rls_block_literal", rls_block_literal_f64, rls_block_literal_f32,
                    args, nargs);
}

PyDoc_STRVAR(trace_of_doc,
"trace_of(P) -> float\n\n"
"Trace of the square float64 or float32 matrix P, summed in index order in its dtype.");

static PyObject *py_trace_of(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    static const Spec spec[] = {{0, "P", REAL_, 2, RO}};
    Args a = {.fn = "trace_of", .count = 0};
    Py_buffer *P;
    PyObject *res = NULL;
    (void)self;
    if (start(&a, nargs, 1)) {
        const int single = is_single(args[0]);
        if (take(&a, args, spec, 1, &P, single ? F32 : F64)
            && need(&a, P, "P", dim(P, 1), dim(P, 1)))
            res = PyFloat_FromDouble(single ? (double)trace_of_f32(dim(P, 0), F(P))
                                            : trace_of_f64(dim(P, 0), D(P)));
    }
    release(&a);
    return res;
}

/* ------------------------------------------------------------------ SVF glue */
/* The arrays svf() and svf_scaled() share (arguments 0 to 7), checked against u (N, m). */
static const Spec svf_spec[] = {
    {0, "u", F64, 2, RO}, {1, "Ad", F64, 2, RO}, {2, "G0", F64, 2, RO}, {3, "G1", F64, 2, RO},
    {4, "x1", F64, 1, RW}, {5, "x2", F64, 1, RW}, {6, "up", F64, 1, RW},
    {7, "primed", I64, 1, RW},
};

static int svf_shapes(Args *a, Py_buffer **b)
{
    const Py_ssize_t m = dim(b[0], 1);
    return need(a, b[1], "Ad", 2, 2) && need(a, b[2], "G0", m, 2) && need(a, b[3], "G1", m, 2)
           && need(a, b[4], "x1", m, -1) && need(a, b[5], "x2", m, -1)
           && need(a, b[6], "up", m, -1) && need(a, b[7], "primed", 1, -1);
}

PyDoc_STRVAR(svf_doc,
"svf(u, Ad, G0, G1, x1, x2, up, primed, f, sf) -> None\n\n"
"Filter every column of u (N, m) row by row, carrying (x1, x2, up) and primed;\n"
"f gets x1 and sf x2 of every row. See canrls.estimation.svf.");

static PyObject *py_svf(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    static const Spec out_spec[] = {{8, "f", F64, 2, RW}, {9, "sf", F64, 2, RW}};
    Args a = {.fn = "svf", .count = 0};
    Py_buffer *b[COUNT(svf_spec) + COUNT(out_spec)];
    Py_buffer **o = b + COUNT(svf_spec);
    PyObject *res = NULL;
    (void)self;
    if (start(&a, nargs, 10) && take(&a, args, svf_spec, COUNT(svf_spec), b, F64)
        && take(&a, args, out_spec, COUNT(out_spec), o, F64) && svf_shapes(&a, b)) {
        const Py_ssize_t N = dim(b[0], 0), m = dim(b[0], 1);
        if (need(&a, o[0], "f", N, m) && need(&a, o[1], "sf", N, m)) {
            Py_BEGIN_ALLOW_THREADS
            svf(N, m, D(b[0]), D(b[1]), D(b[2]), D(b[3]), D(b[4]), D(b[5]), D(b[6]), I(b[7]),
                D(o[0]), D(o[1]));
            Py_END_ALLOW_THREADS
            res = Py_NewRef(Py_None);
        }
    }
    release(&a);
    return res;
}

PyDoc_STRVAR(svf_scaled_doc,
"svf_scaled(u, Ad, G0, G1, x1, x2, up, primed, deriv, scale, y, phi) -> None\n\n"
"svf() writing one output per column: x2 where deriv (bool, m) else x1, times\n"
"scale (m); column 0 into y (N), the others into phi (N, m-1).");

static PyObject *py_svf_scaled(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    static const Spec out_spec[] = {{8, "deriv", BOOL, 1, RO}, {9, "scale", F64, 1, RO},
                                    {10, "y", F64, 1, RW}, {11, "phi", F64, 2, RW}};
    Args a = {.fn = "svf_scaled", .count = 0};
    Py_buffer *b[COUNT(svf_spec) + COUNT(out_spec)];
    Py_buffer **o = b + COUNT(svf_spec);
    PyObject *res = NULL;
    (void)self;
    if (start(&a, nargs, 12) && take(&a, args, svf_spec, COUNT(svf_spec), b, F64)
        && take(&a, args, out_spec, COUNT(out_spec), o, F64) && svf_shapes(&a, b)) {
        const Py_ssize_t N = dim(b[0], 0), m = dim(b[0], 1);
        if (m < 1)
            PyErr_Format(PyExc_ValueError, "svf_scaled: u must have a column (the output)");
        else if (need(&a, o[0], "deriv", m, -1) && need(&a, o[1], "scale", m, -1)
                 && need(&a, o[2], "y", N, -1) && need(&a, o[3], "phi", N, m - 1)) {
            Py_BEGIN_ALLOW_THREADS
            svf_scaled(N, m, D(b[0]), D(b[1]), D(b[2]), D(b[3]), D(b[4]), D(b[5]), D(b[6]),
                       I(b[7]), U(o[0]), D(o[1]), D(o[2]), D(o[3]));
            Py_END_ALLOW_THREADS
            res = Py_NewRef(Py_None);
        }
    }
    release(&a);
    return res;
}

/* ------------------------------------------------------------ selection glue */
PyDoc_STRVAR(select_doc,
"select(t, omega, gap, warm, min_speed, max_speed, state, restart, use)\n"
"    -> (restarts, used)\n\n"
"Mark the restarts (gaps) and the rows to use of a block; state = [last t, warm-up\n"
"left, last omega] is carried. See canrls.estimation.selection.");

static PyObject *py_select(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    static const Spec spec[] = {{0, "t", F64, 1, RO}, {1, "omega", F64, 1, RO},
                                {6, "state", F64, 1, RW}, {7, "restart", BOOL, 1, RW},
                                {8, "use", BOOL, 1, RW}};
    Args a = {.fn = "select", .count = 0};
    Py_buffer *b[COUNT(spec)];
    double gap, min_speed, max_speed;
    int64_t warm;
    PyObject *res = NULL;
    (void)self;
    if (start(&a, nargs, 9) && as_double(args[2], &gap) && as_int64(args[3], &warm)
        && as_double(args[4], &min_speed) && as_double(args[5], &max_speed)
        && take(&a, args, spec, COUNT(spec), b, F64)) {
        const Py_ssize_t N = dim(b[0], 0);
        if (need(&a, b[1], "omega", N, -1) && need(&a, b[2], "state", 3, -1)
            && need(&a, b[3], "restart", N, -1) && need(&a, b[4], "use", N, -1)) {
            Py_ssize_t restarts, used;
            Py_BEGIN_ALLOW_THREADS
            select_rows(N, D(b[0]), D(b[1]), gap, warm, min_speed, max_speed, D(b[2]),
                        U(b[3]), U(b[4]), &restarts, &used);
            Py_END_ALLOW_THREADS
            res = Py_BuildValue("(nn)", restarts, used);
        }
    }
    release(&a);
    return res;
}

PyDoc_STRVAR(nothing_to_fill_doc,
"nothing_to_fill(t, has_last, last_t, dt, max_gap) -> bool\n\n"
"True when no step between the samples t (from last_t if has_last) misses a period.");

static PyObject *py_nothing_to_fill(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    static const Spec spec[] = {{0, "t", F64, 1, RO}};
    Args a = {.fn = "nothing_to_fill", .count = 0};
    Py_buffer *t;
    int has_last;
    double last_t, dt, max_gap;
    PyObject *res = NULL;
    (void)self;
    if (start(&a, nargs, 5) && as_bool(args[1], &has_last) && as_double(args[2], &last_t)
        && as_double(args[3], &dt) && as_double(args[4], &max_gap)
        && take(&a, args, spec, 1, &t, F64) && at_least(&a, t, "t", 1, "at least one sample"))
        res = PyBool_FromLong(nothing_to_fill(dim(t, 0), D(t), has_last, last_t, dt, max_gap));
    release(&a);
    return res;
}

/* ------------------------------------------------------------- unwrap glue */
PyDoc_STRVAR(unwrap_doc,
"unwrap(p, period, turns, last, out) -> int\n\n"
"Unwrapped positions p into out from the turn count and the previous sample (nan:\n"
"none); the turn count at the end. See canrls.estimation.model.PositionUnwrapper.");

static PyObject *py_unwrap(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    static const Spec spec[] = {{0, "p", F64, 1, RO}, {4, "out", F64, 1, RW}};
    Args a = {.fn = "unwrap", .count = 0};
    Py_buffer *b[COUNT(spec)];
    double period, last;
    int64_t turns;
    PyObject *res = NULL;
    (void)self;
    if (start(&a, nargs, 5) && as_double(args[1], &period) && as_int64(args[2], &turns)
        && as_double(args[3], &last) && take(&a, args, spec, COUNT(spec), b, F64)
        && at_least(&a, b[0], "p", 1, "at least one sample")
        && need(&a, b[1], "out", dim(b[0], 0), -1)) {
        Py_BEGIN_ALLOW_THREADS
        turns = unwrap(dim(b[0], 0), D(b[0]), period, turns, last, D(b[1]));
        Py_END_ALLOW_THREADS
        res = PyLong_FromLongLong(turns);
    }
    release(&a);
    return res;
}

/* ---------------------------------------------------------- pipeline glue */
/* The arrays accumulate() and bookkeeping() share: phi (N, n), y, use, M, v, s. */
static int sums_shapes(Args *a, Py_buffer *phi, Py_buffer *y, Py_buffer *use, Py_buffer *M,
                       Py_buffer *v, Py_buffer *s)
{
    const Py_ssize_t N = dim(phi, 0), n = dim(phi, 1);
    return need(a, y, "y", N, -1) && need(a, use, "use", N, -1) && need(a, M, "M", n, n)
           && need(a, v, "v", n, -1) && need(a, s, "s", 3, -1);
}

PyDoc_STRVAR(accumulate_doc,
"accumulate(phi, y, use, M, v, s) -> None\n\n"
"Sums over the used rows: M += phi phi' (upper triangle), v += phi y,\n"
"s += [1, y, y^2].");

static PyObject *py_accumulate(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    static const Spec spec[] = {{0, "phi", F64, 2, RO}, {1, "y", F64, 1, RO},
                                {2, "use", BOOL, 1, RO}, {3, "M", F64, 2, RW},
                                {4, "v", F64, 1, RW}, {5, "s", F64, 1, RW}};
    Args a = {.fn = "accumulate", .count = 0};
    Py_buffer *b[COUNT(spec)];
    PyObject *res = NULL;
    (void)self;
    if (start(&a, nargs, 6) && take(&a, args, spec, COUNT(spec), b, F64)
        && sums_shapes(&a, b[0], b[1], b[2], b[3], b[4], b[5])) {
        Py_BEGIN_ALLOW_THREADS
        accumulate(dim(b[0], 0), dim(b[0], 1), D(b[0]), D(b[1]), U(b[2]), D(b[3]), D(b[4]),
                   D(b[5]));
        Py_END_ALLOW_THREADS
        res = Py_NewRef(Py_None);
    }
    release(&a);
    return res;
}

PyDoc_STRVAR(bookkeeping_doc,
"bookkeeping(phi, y, use, eps_u, epsq_u, lsb, flags_u, flagsq_u, M, v, s, beta,\n"
"            rms_state, s_y, y_out, eps, eps_fixed, flags, rms) -> int\n\n"
"After the estimators: spread the used rows' errors and flags over the block, run\n"
"the residual RMS, write y, the errors and the RMS in the output unit (x 2**s_y),\n"
"accumulate the sums; the float WINDUP count. See canrls.estimation.pipeline.");

static PyObject *py_bookkeeping(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    static const Spec spec[] = {
        {0, "phi", F64, 2, RO}, {1, "y", F64, 1, RO}, {2, "use", BOOL, 1, RO},
        {8, "M", F64, 2, RW}, {9, "v", F64, 1, RW}, {10, "s", F64, 1, RW},
        {3, "eps_u", F64, 1, RO}, {4, "epsq_u", I64, 1, RO}, {6, "flags_u", U8, 1, RO},
        {7, "flagsq_u", U8, 1, RO}, {12, "rms_state", F64, 1, RW}, {14, "y_out", F64, 1, RW},
        {15, "eps", F64, 1, RW}, {16, "eps_fixed", F64, 1, RW}, {17, "flags", U8, 1, RW},
        {18, "rms", F64, 1, RW},
    };
    Args a = {.fn = "bookkeeping", .count = 0};
    Py_buffer *b[COUNT(spec)];
    double lsb, beta;
    int64_t s_y;
    PyObject *res = NULL;
    (void)self;
    if (start(&a, nargs, 19) && as_double(args[5], &lsb) && as_double(args[11], &beta)
        && as_int64(args[13], &s_y) && take(&a, args, spec, COUNT(spec), b, F64)
        && sums_shapes(&a, b[0], b[1], b[2], b[3], b[4], b[5])) {
        const Py_ssize_t N = dim(b[0], 0);
        /* the used rows: as many as eps_u and the others must hold */
        Py_ssize_t used = 0;
        for (Py_ssize_t k = 0; k < N; k++)
            used += U(b[2])[k] != 0;
        const char *what = "as many rows as use has used rows";
        if (at_least(&a, b[6], "eps_u", used, what) && at_least(&a, b[7], "epsq_u", used, what)
            && at_least(&a, b[8], "flags_u", used, what)
            && at_least(&a, b[9], "flagsq_u", used, what)
            && need(&a, b[10], "rms_state", 1, -1) && need(&a, b[11], "y_out", N, -1)
            && need(&a, b[12], "eps", N, -1) && need(&a, b[13], "eps_fixed", N, -1)
            && need(&a, b[14], "flags", N, -1) && need(&a, b[15], "rms", N, -1)) {
            Py_ssize_t windup;
            Py_BEGIN_ALLOW_THREADS
            windup = bookkeeping(N, dim(b[0], 1), D(b[0]), D(b[1]), U(b[2]), D(b[6]), I(b[7]),
                                 lsb, U(b[8]), U(b[9]), D(b[3]), D(b[4]), D(b[5]), beta,
                                 D(b[10]), s_y, D(b[11]), D(b[12]), D(b[13]), U(b[14]),
                                 D(b[15]));
            Py_END_ALLOW_THREADS
            res = PyLong_FromSsize_t(windup);
        }
    }
    release(&a);
    return res;
}

PyDoc_STRVAR(sincos_doc,
"sincos(a, q, out)\n\n"
"out[i, 2j] = sin(q[j] a[i]), out[i, 2j + 1] = cos(q[j] a[i]): the harmonic columns of\n"
"the diagnosis's order spectrum (canrls.diagnosis.residual.harmonic_fit).");

static PyObject *py_sincos(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    static const Spec spec[] = {{0, "a", F64, 1, RO}, {1, "q", F64, 1, RO},
                                {2, "out", F64, 2, RW}};
    Args a = {.fn = "sincos", .count = 0};
    Py_buffer *b[COUNT(spec)];
    PyObject *res = NULL;
    (void)self;
    if (start(&a, nargs, 3) && take(&a, args, spec, COUNT(spec), b, F64)
        && need(&a, b[2], "out", dim(b[0], 0), 2 * dim(b[1], 0))) {
        Py_BEGIN_ALLOW_THREADS
        sincos_columns(dim(b[0], 0), dim(b[1], 0), D(b[0]), D(b[1]), D(b[2]));
        Py_END_ALLOW_THREADS
        res = Py_NewRef(Py_None);
    }
    release(&a);
    return res;
}

/* ================================================================== module */
static PyMethodDef methods[] = {
    {"rls_block_symmetric", (PyCFunction)(void (*)(void))py_rls_block_symmetric,
     METH_FASTCALL, rls_block_symmetric_doc},
    {"rls_block_literal", (PyCFunction)(void (*)(void))py_rls_block_literal, METH_FASTCALL,
     rls_block_literal_doc},
    {"trace_of", (PyCFunction)(void (*)(void))py_trace_of, METH_FASTCALL, trace_of_doc},
    {"svf", (PyCFunction)(void (*)(void))py_svf, METH_FASTCALL, svf_doc},
    {"svf_scaled", (PyCFunction)(void (*)(void))py_svf_scaled, METH_FASTCALL, svf_scaled_doc},
    {"select", (PyCFunction)(void (*)(void))py_select, METH_FASTCALL, select_doc},
    {"nothing_to_fill", (PyCFunction)(void (*)(void))py_nothing_to_fill, METH_FASTCALL,
     nothing_to_fill_doc},
    {"unwrap", (PyCFunction)(void (*)(void))py_unwrap, METH_FASTCALL, unwrap_doc},
    {"accumulate", (PyCFunction)(void (*)(void))py_accumulate, METH_FASTCALL, accumulate_doc},
    {"bookkeeping", (PyCFunction)(void (*)(void))py_bookkeeping, METH_FASTCALL,
     bookkeeping_doc},
    {"sincos", (PyCFunction)(void (*)(void))py_sincos, METH_FASTCALL, sincos_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT,
    .m_name = "canrls._kernels",
    .m_doc = "The per-sample float kernels of canrls's estimation (C, see src/canrls/c/host/kernels.c).",
    .m_size = 0,
    .m_methods = methods,
};

PyMODINIT_FUNC PyInit__kernels(void)
{
    PyObject *m = PyModule_Create(&module);
    if (!m)
        return NULL;
    if (PyModule_AddIntConstant(m, "FLAG_WINDUP", FLAG_WINDUP) < 0
        || PyModule_AddIntConstant(m, "FLAG_FROZEN", FLAG_FROZEN) < 0
        || PyModule_AddIntConstant(m, "FLAG_NONFINITE", FLAG_NONFINITE) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
